"""Pieces shared by the frontends: image loading with undistortion, SIFT matching with
geometric verification, and the co-visibility graph."""

import cv2
import numpy as np

from calib3r_graph.errors import InputError

FULL_CONF_ANGLE_DEG = 5.0  # triangulation angle at which a depth gets full confidence


def load_gray(path):
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError(path, "unreadable image")
    return img


def undistort_maps(camera):
    """(map1, map2) to a pinhole grid with the same K, or None for a PINHOLE camera."""
    if not np.any(camera.dist):
        return None
    return cv2.initUndistortRectifyMap(camera.K, camera.dist, None, camera.K, (camera.width, camera.height),
                                       cv2.CV_32FC1)


def sift_features(gray, n_features=4000):
    sift = cv2.SIFT_create(nfeatures=n_features)
    kp, desc = sift.detectAndCompute(gray, None)
    pts = np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2)
    return pts, (desc if desc is not None else np.zeros((0, 128), np.float32))


def match_verified(feat_a, feat_b, K_a, K_b, ratio=0.8, ransac_px=1.0, min_inliers=30):
    """Mutual ratio-test SIFT matches, verified by an essential matrix (RANSAC).

    Returns (uv_a, uv_b, conf) or None. conf = 1 - distance ratio (ambiguous matches count less).
    """
    (pa, da), (pb, db) = feat_a, feat_b
    if len(da) < 8 or len(db) < 8:
        return None
    bf = cv2.BFMatcher(cv2.NORM_L2)
    knn = bf.knnMatch(da, db, k=2)
    good = [(m.queryIdx, m.trainIdx, m.distance / max(n.distance, 1e-9)) for m, n in
            (x for x in knn if len(x) == 2) if m.distance < ratio * n.distance]
    if len(good) < min_inliers:
        return None
    ia, ib, r = map(np.array, zip(*good))
    # mutual check: keep the best a for each b
    order = np.argsort(r)
    _, first = np.unique(ib[order], return_index=True)
    keep = order[first]
    ia, ib, r = ia[keep], ib[keep], r[keep]
    if len(ia) < min_inliers:
        return None
    na = cv2.undistortPoints(pa[ia].reshape(-1, 1, 2), K_a, None).reshape(-1, 2)
    nb = cv2.undistortPoints(pb[ib].reshape(-1, 1, 2), K_b, None).reshape(-1, 2)
    f = 0.5 * (K_a[0, 0] + K_b[0, 0])
    E, mask = cv2.findEssentialMat(na, nb, np.eye(3), cv2.RANSAC, 0.999, ransac_px / f)
    if E is None or mask is None:
        return None
    inl = mask.ravel().astype(bool)
    if inl.sum() < min_inliers:
        return None
    return pa[ia[inl]], pb[ib[inl]], (1.0 - r[inl]).clip(0.05, 1.0)


def covisibility_edges(scores: dict, views, k: int, same_frame_edges=True, min_score=1):
    """Top-k neighbours per view by score, plus every same-frame pair of a rig."""
    edges = set()
    for v in views:
        nb = sorted(((s, tuple(sorted(e))) for e, s in scores.items() if v in e and s >= min_score), reverse=True)
        edges.update(e for _, e in nb[:k])
    if same_frame_edges:
        edges.update(e for e, s in scores.items() if s >= min_score and e[0].split("/")[1] == e[1].split("/")[1])
    return sorted(edges)


def aggregate_pointmaps(depths: np.ndarray, confs: np.ndarray):
    """Canonical depth of a view from its P pairwise predictions (Calib3R eq. 1):
    ``d = sum_e C_e d_e / sum_e C_e`` per pixel; the confidence is the mean of the C_e.
    depths, confs: (P, H, W); invalid entries (depth <= 0 or non-finite) carry no weight."""
    depths = np.asarray(depths, dtype=np.float64)
    valid = np.isfinite(depths) & (depths > 0)
    w = np.where(valid, np.maximum(np.nan_to_num(confs, nan=0.0, posinf=0.0), 0), 0.0)
    d = np.where(valid, depths, 0.0)
    total = w.sum(0)
    depth = (w * d).sum(0) / np.where(total > 0, total, 1.0)
    return depth.astype(np.float32), (total / len(depths)).astype(np.float32)
