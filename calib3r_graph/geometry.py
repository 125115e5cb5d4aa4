"""Closed-form geometry used by initialisation: Sim(3) alignment with RANSAC, rotation means."""

import gtsam
import numpy as np


def umeyama(src: np.ndarray, dst: np.ndarray, weights=None):
    """Sim(3) (s, R, t) minimising sum w |dst - (s R src + t)|^2 (Umeyama 1991)."""
    w = np.ones(len(src)) if weights is None else weights
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    xs, xd = src - mu_s, dst - mu_d
    cov = (xd * w[:, None]).T @ xs
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var_s = w @ (xs**2).sum(1)
    s = np.trace(np.diag(S) @ D) / var_s
    t = mu_d - s * R @ mu_s
    return s, R, t


def umeyama_batch(src: np.ndarray, dst: np.ndarray):
    """Umeyama for a batch of minimal samples: src, dst (H, k, 3) -> s (H,), R (H, 3, 3), t (H, 3)."""
    mu_s, mu_d = src.mean(1), dst.mean(1)
    xs, xd = src - mu_s[:, None], dst - mu_d[:, None]
    cov = np.einsum("hki,hkj->hij", xd, xs) / src.shape[1]
    U, S, Vt = np.linalg.svd(cov)
    sign = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    D = np.ones((len(src), 3))
    D[:, 2] = sign
    R = np.einsum("hij,hj,hjk->hik", U, D, Vt)
    var_s = (xs**2).sum((1, 2)) / src.shape[1]
    s = (S * D).sum(1) / np.maximum(var_s, 1e-300)
    t = mu_d - s[:, None] * np.einsum("hij,hj->hi", R, mu_s)
    return s, R, t


def ransac_sim3(src, dst, rel_threshold=0.03, iterations=128, rng=None, max_score_points=300):
    """Robust Sim(3) dst ~ s R src + t; hypotheses are generated and scored in one batch.

    Inliers: residual < rel_threshold * median |dst| (relative, because the frontend's
    depth unit is unknown). Returns (s, R, t, inlier mask) or None.
    """
    rng = rng or np.random.default_rng(0)
    n = len(src)
    thr = rel_threshold * np.median(np.linalg.norm(dst, axis=1))
    samples = rng.integers(0, n, size=(iterations, 3))
    distinct = (samples[:, 0] != samples[:, 1]) & (samples[:, 1] != samples[:, 2]) & (samples[:, 0] != samples[:, 2])
    samples = samples[distinct]
    with np.errstate(all="ignore"):  # degenerate (collinear) samples give non-finite models, dropped below
        s, R, t = umeyama_batch(src[samples], dst[samples])
    ok = np.isfinite(s) & (s > 0) & np.isfinite(t).all(1)
    if not ok.any():
        return None
    s, R, t = s[ok], R[ok], t[ok]
    score_idx = rng.choice(n, min(n, max_score_points), replace=False)
    pred = s[:, None, None] * (R @ src[score_idx].T) + t[:, :, None]  # (H, 3, M)
    diff = pred - dst[score_idx].T
    count = (np.einsum("him,him->hm", diff, diff) < thr * thr).sum(1)
    b = int(np.argmax(count))
    best = np.linalg.norm(dst - (s[b] * src @ R[b].T + t[b]), axis=1) < thr
    for _ in range(3):  # refit on inliers, then re-select
        if best.sum() < 3:
            return None
        s1, R1, t1 = umeyama(src[best], dst[best])
        best = np.linalg.norm(dst - (s1 * src @ R1.T + t1), axis=1) < thr
    if best.sum() < 3:
        return None
    return s1, R1, t1, best


def project_to_so3(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def hand_eye_rotation(alphas: np.ndarray, betas: np.ndarray) -> tuple[np.ndarray, float]:
    """R_X from the rotation axes (angle-scaled) of AX = XB: alpha_i = R_X beta_i (Wahba, by Kabsch).

    Returns R_X and the mean axis residual in degrees.
    """
    R = project_to_so3(np.einsum("ni,nj->ij", alphas, betas))
    return R, float(np.degrees(np.mean(np.linalg.norm(alphas - betas @ R.T, axis=1))))


def mean_pose(poses) -> gtsam.Pose3:
    """Chordal mean rotation and mean translation."""
    R = project_to_so3(sum(p.rotation().matrix() for p in poses))
    t = np.mean([p.translation() for p in poses], axis=0)
    return gtsam.Pose3(gtsam.Rot3(R), t)


def rotation_angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def pose_error(est: gtsam.Pose3, ref: gtsam.Pose3) -> tuple[float, float]:
    """(translation error in metres, rotation error in degrees)."""
    d = ref.between(est)
    return float(np.linalg.norm(est.translation() - ref.translation())), rotation_angle_deg(d.rotation().matrix())
