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


def ransac_sim3(src, dst, rel_threshold=0.03, iterations=200, rng=None):
    """Robust Sim(3) dst ~ s R src + t. Inliers: residual < rel_threshold * |dst - centroid| scale.

    Returns (s, R, t, inlier mask); the threshold is relative because the frontend's
    depth unit is unknown.
    """
    rng = rng or np.random.default_rng(0)
    n = len(src)
    scale = np.median(np.linalg.norm(dst, axis=1))
    thr = rel_threshold * scale
    best = None
    for _ in range(iterations):
        idx = rng.choice(n, 3, replace=False)
        s, R, t = umeyama(src[idx], dst[idx])
        if not np.isfinite(s) or s <= 0:
            continue
        inl = np.linalg.norm(dst - (s * src @ R.T + t), axis=1) < thr
        if best is None or inl.sum() > best.sum():
            best = inl
    if best is None or best.sum() < 3:
        return None
    for _ in range(3):  # refit on inliers, then re-select
        s, R, t = umeyama(src[best], dst[best])
        best = np.linalg.norm(dst - (s * src @ R.T + t), axis=1) < thr
        if best.sum() < 3:
            return None
    return s, R, t, best


def project_to_so3(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


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
