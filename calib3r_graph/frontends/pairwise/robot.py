"""The robot's help to the pairwise frontend, never as ground truth (step 3 in ``frontend.py``): pairs
whose relative motion disagrees with the flange's are dropped (:func:`robot_consistent`), and the
pairs of weakly connected views are matched again within the epipolar band the robot predicts
(:func:`rescue_pairs`)."""

import itertools
import logging

import cv2
import gtsam
import numpy as np

from factors._lie import skew
from calib3r_graph.frontends.pairwise.geometry import two_view_geometry
from calib3r_graph.frontends.pairwise.options import PairwiseOptions, _map_with_progress
from calib3r_graph.geometry import hand_eye_rotation, rotation_angle_deg
from calib3r_graph.io.predictions import split_view_id

log = logging.getLogger(__name__)


def _rotvec(R):
    return cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()


def robot_consistent(geoms: dict, base_T_ee: dict, opt: PairwiseOptions, seed=0) -> tuple[dict, dict]:
    """The pairs whose relative motion agrees with the robot's, and what was learnt.

    Per camera, over the pairs of its own views (pairs across the cameras of a rig are kept
    unchecked): (1) the camera's and the flange's relative rotation angles must agree (true for
    any hand-eye rotation); (2) a rough hand-eye rotation, RANSAC over the pairs' rotation axes,
    must map the flange's relative rotation onto the pair's; (3) with a rough hand-eye
    translation, RANSAC over triples of pairs, the pair's translation direction must agree. None
    lets the robot set anything. Returns ({pair: geometry}, info); ``info["hand_eye"][camera]``
    holds the rough ``rotation`` (3x3) and ``translation`` (m) where they could be found."""
    info = {"angle_rejected": [], "rotation_rejected": [], "translation_rejected": [], "hand_eye": {}}
    cam = lambda v: split_view_id(v)[0]  # noqa: E731
    kept = {ab: g for ab, g in geoms.items() if g is not None and cam(ab[0]) != cam(ab[1])}
    rng = np.random.default_rng(seed)
    for c in sorted({cam(a) for a, b in geoms if cam(a) == cam(b)}):
        group = {ab: g for ab, g in geoms.items() if g is not None and cam(ab[0]) == c == cam(ab[1])}
        kept.update(_robot_checks(group, base_T_ee, opt, info, info["hand_eye"].setdefault(c, {}), rng))
    for k in ("angle_rejected", "rotation_rejected", "translation_rejected"):
        if info[k]:
            log.info("pairwise: %d pair(s) disagree with the robot's motion (%s): %s", len(info[k]),
                     k.split("_")[0], ", ".join(info[k][:6]) + (" ..." if len(info[k]) > 6 else ""))
    return kept, info


def _robot_checks(geoms: dict, base_T_ee: dict, opt: PairwiseOptions, info: dict, hand_eye: dict, rng) -> dict:
    """:func:`robot_consistent` for the pairs of one camera."""
    kept = {}
    alphas, betas, names = [], [], []
    for (a, b), g in geoms.items():
        if g is None:
            continue
        A = base_T_ee[split_view_id(a)[1]].between(base_T_ee[split_view_id(b)[1]]).rotation().matrix()
        ang_ee, ang_cam = rotation_angle_deg(A), rotation_angle_deg(g.R)
        if abs(ang_ee - ang_cam) > opt.angle_tol_deg:
            info["angle_rejected"].append(f"{a}-{b} ({ang_cam:.1f} vs {ang_ee:.1f} deg)")
            continue
        kept[(a, b)] = g
        if ang_ee > 3.0:
            alphas.append(_rotvec(A))
            betas.append(_rotvec(g.R.T))  # B = cam_a^-1 cam_b has rotation R^T (x_b = R x_a + t)
            names.append((a, b))
    if len(alphas) >= 3:
        alphas, betas = np.array(alphas), np.array(betas)
        na = alphas / np.linalg.norm(alphas, axis=1, keepdims=True)
        best, best_count = None, 0
        cand = list(itertools.combinations(range(len(alphas)), 2))
        if len(cand) > 300:
            cand = [cand[i] for i in rng.choice(len(cand), 300, replace=False)]
        I, J = np.array(cand).T
        apart = np.linalg.norm(np.cross(na[I], na[J]), axis=1) >= np.sin(np.radians(10))  # one call, not per pair
        I, J = I[apart], J[apart]  # parallel axes do not fix a rotation
        if len(I):  # the first hypothesis with the most inliers (and at least one)
            R_all = _hand_eye_rotations(alphas[np.c_[I, J]], betas[np.c_[I, J]])
            err = np.degrees(np.linalg.norm(alphas[None] - betas[None] @ R_all.transpose(0, 2, 1), axis=2))
            count = (err < opt.rotation_tol_deg).sum(1)
            k = int(np.argmax(count))
            if count[k] > best_count:
                best, best_count = R_all[k], int(count[k])
        if best is not None:
            err = np.degrees(np.linalg.norm(alphas - betas @ best.T, axis=1))
            inl = err < opt.rotation_tol_deg
            R_X, res = hand_eye_rotation(alphas[inl], betas[inl])
            err = np.degrees(np.linalg.norm(alphas - betas @ R_X.T, axis=1))
            hand_eye["rotation"] = R_X.tolist()
            hand_eye["axis_residual_deg"] = res
            for (a, b), e in zip(names, err):
                if e > opt.rotation_tol_deg:
                    info["rotation_rejected"].append(f"{a}-{b} ({e:.1f} deg)")
                    kept.pop((a, b))
            _translation_check(kept, base_T_ee, R_X, opt, info, hand_eye, rng)
    return kept


def _hand_eye_rotations(alphas, betas):
    """``geometry.hand_eye_rotation``'s R_X for a stack of hypotheses, alphas and betas (K, n, 3): the
    same operations (Kabsch: the SVD of sum alpha beta^T, projected onto SO(3)) on stacked arrays,
    one call each instead of K (the RANSAC's ~300 hypotheses cost 17 ms one by one)."""
    U, _, Vt = np.linalg.svd(np.einsum("kni,knj->kij", alphas, betas))
    D = np.zeros((len(U), 3, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1
    D[:, 2, 2] = np.sign(np.linalg.det(U @ Vt))
    return U @ D @ Vt


def _translation_check(kept: dict, base_T_ee: dict, R_X, opt: PairwiseOptions, info: dict, hand_eye: dict, rng):
    """Drop pairs whose translation direction disagrees with the robot's motion.

    With the rough hand-eye rotation R_X, AX = XB gives for each pair
    ``(R_A - I) t_X - lambda_e R_X t_e = -t_A`` (t_e: the pair's unit translation of B, lambda_e
    its unknown length). A RANSAC over triples of pairs finds t_X; a pair is an outlier when the
    direction it measures is more than ``translation_tol_deg`` from the one the robot and t_X
    predict. Pure translations need no t_X: their direction is R_X^T t_A."""
    keys = list(kept)
    if len(keys) < 4:
        return
    RA, tA, tB = [], [], []
    for a, b in keys:
        A = base_T_ee[split_view_id(a)[1]].between(base_T_ee[split_view_id(b)[1]])
        g = kept[(a, b)]
        RA.append(A.rotation().matrix())
        tA.append(A.translation())
        tB.append(R_X @ (-g.R.T @ g.t))  # B = cam_a^-1 cam_b: translation -R^T t, in ee axes
    RA, tA, tB = np.array(RA), np.array(tA), np.array(tB)
    M = RA - np.eye(3)

    def directions_error(t_X):
        pred = np.einsum("nij,j->ni", M, t_X) + tA
        norm = np.linalg.norm(pred, axis=1)
        cos = (pred * tB).sum(1) / np.maximum(norm, 1e-12)
        return np.degrees(np.arccos(np.clip(cos, -1, 1))), norm

    fit = _translation_fit(M, tA, tB)

    rotating = np.flatnonzero(np.linalg.norm(M, axis=(1, 2)) > np.radians(3))
    if len(rotating) < 3:
        return
    T = fit(np.array([rng.choice(rotating, 3, replace=False) for _ in range(200)]))
    # every hypothesis' directions at once (the same einsum per hypothesis); the first with the most inliers
    pred = np.einsum("nij,kj->kni", M, T) + tA
    cos = (pred * tB).sum(2) / np.maximum(np.linalg.norm(pred, axis=2), 1e-12)
    best = T[int(np.argmax((np.degrees(np.arccos(np.clip(cos, -1, 1))) < opt.translation_tol_deg).sum(1)))]
    err, _ = directions_error(best)
    inl = np.flatnonzero(err < opt.translation_tol_deg)
    if len(inl) >= 3:
        err, _ = directions_error(fit(inl))
    hand_eye["translation"] = best.tolist()
    for (a, b), e in zip(keys, err):
        if e > opt.translation_tol_deg:
            info["translation_rejected"].append(f"{a}-{b} ({e:.1f} deg)")
            kept.pop((a, b))


def _translation_fit(M, tA, tB):
    """t_X from sets of pairs: ``fit(idx)``, idx (..., n) indices into the pairs, gives the t_X (..., 3)
    of each set that minimises sum_e |M_e t_X + t_A - lambda_e t_e|^2 over t_X and the lambdas.
    Each lambda_e minimised out, that is the 3x3 normal equations of P_e (M_e t_X + t_A) = 0 with
    P_e = I - u u^T the projection orthogonal to t_e: the minimiser of the full (3n, 3 + n) system,
    for every set in one batched solve (one lstsq per triple cost 57 ms for the RANSAC's 200, 2-3
    times a live update). A degenerate set gives some t_X (pinv), no error."""
    u = tB / np.maximum(np.linalg.norm(tB, axis=1, keepdims=True), 1e-12)
    PM = M - u[:, :, None] * np.einsum("ni,nij->nj", u, M)[:, None, :]  # P_e M_e
    Pt = tA - u * (u * tA).sum(1, keepdims=True)  # P_e t_A

    def fit(idx):
        N = np.einsum("...nji,...njk->...ik", PM[idx], PM[idx])
        r = -np.einsum("...nji,...nj->...i", PM[idx], Pt[idx])
        return np.einsum("...ij,...j->...i", np.linalg.pinv(N), r)

    return fit


def rescue_pairs(ds, feats: dict, candidates, kept: dict, robot_info: dict, opt: PairwiseOptions, progress=True,
                 workers=2) -> dict:
    """Pairs that failed or disagreed with the robot, tried again with robot-guided matching.

    For views with fewer than ``opt.rescue_below`` usable pairs: the rough hand-eye
    (:func:`robot_consistent`) and the flange motion predict the pair's epipolar geometry;
    putative matches are searched within ``opt.rescue_band_deg`` of it (a repeated texture such
    as a chessboard has too many look-alikes in the whole image for the ratio test), then the
    pose is estimated from those matches alone, as for any pair, and must pass the same robot
    checks afterwards. Returns {pair: geometry} of the pairs that gave a geometry."""
    X = {c: gtsam.Pose3(gtsam.Rot3(np.array(he["rotation"])), np.array(he["translation"]))
         for c, he in robot_info["hand_eye"].items() if "rotation" in he and "translation" in he}
    count = {v: 0 for v in feats}
    for a, b in kept:
        count[a] += 1
        count[b] += 1
    cam = lambda v: split_view_id(v)[0]  # noqa: E731
    todo = [(a, b) for a, b in candidates if (a, b) not in kept and min(count[a], count[b]) < opt.rescue_below
            and cam(a) == cam(b) and cam(a) in X]
    if not todo:
        return {}
    K = {v: ds.cameras[split_view_id(v)[0]].K for v in feats}

    def one(ab):
        a, b = ab
        A = ds.base_T_ee[split_view_id(a)[1]].between(ds.base_T_ee[split_view_id(b)[1]])
        B = X[cam(a)].inverse().compose(A).compose(X[cam(a)])  # a_T_b, predicted
        R = B.rotation().matrix().T
        t = -R @ B.translation()
        if np.linalg.norm(t) < 1e-6:
            return ab, None
        E = skew(t / np.linalg.norm(t)) @ R
        px = 0.5 * (K[a][0, 0] + K[b][0, 0]) * np.tan(np.radians(opt.rescue_band_deg))
        return ab, two_view_geometry(feats[a], feats[b], K[a], K[b], opt, a, b, prior_E=E, prior_px=px)

    out = {ab: g for ab, g in _map_with_progress(one, todo, "pairwise: robot-guided matching", progress,
                                                   workers).items() if g is not None}
    log.info("pairwise: robot-guided matching gave %d of %d pair(s) of weakly connected views", len(out), len(todo))
    return out
