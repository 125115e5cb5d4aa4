"""The pairwise frontend's two-view geometry, once per chosen pair (step 2 in ``frontend.py``): mutual
ratio-test matches, essential-matrix RANSAC, guided matching along the epipolar lines, the pose
refined (Sampson, Huber), Sampson correction and triangulation; cached on disk per pair of images
and options."""

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from factors._lie import skew
from calib3r_graph.frontends.pairwise.options import (Features, PairGeometry, PairwiseOptions, _digest, _image_key,
                                                      _map_with_progress, read_npz)
from calib3r_graph.io.output import atomic_savez
from calib3r_graph.io.predictions import split_view_id


def _mutual_ratio(S, ratio):
    """Mutual best matches passing the ratio test, from a similarity matrix (a rows, b columns):
    (ia, ib, distance ratio). RootSIFT descriptors have unit norm, so ``|a - b|^2 = 2 - 2 a.b``."""
    rows = np.arange(S.shape[0])
    best = S.argmax(1)
    s1 = S[rows, best]
    S[rows, best] = -np.inf
    s2 = S.max(1)
    S[rows, best] = s1
    d1 = np.sqrt(np.maximum(2 - 2 * s1, 0))
    d2 = np.sqrt(np.maximum(2 - 2 * s2, 0))
    r = d1 / np.maximum(d2, 1e-9)
    keep = np.flatnonzero(r < ratio)
    # mutual check: each survivor is its column's best. One max over all columns, not a gather of the
    # survivors' columns (strided: 42 -> 23 ms a pair on rwhe_kuka_1's 2700 features, about 270
    # survivors; the same matches) nor an argmax along them (the slow axis: 0.4 s at 4000 x 4000)
    keep = keep[S.max(0)[best[keep]] <= s1[keep]]
    return rows[keep], best[keep], r[keep]


def sampson_correction(E, xa, xb):
    """The smallest (first-order) moves of xa, xb (normalised, (n, 2)) onto x_b^T E x_a = 0."""
    ha, hb = np.c_[xa, np.ones(len(xa))], np.c_[xb, np.ones(len(xb))]
    Ea, Eb = ha @ E.T, hb @ E
    k = (hb * Ea).sum(1) / (Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Eb[:, 0] ** 2 + Eb[:, 1] ** 2)
    return xa - k[:, None] * Eb[:, :2], xb - k[:, None] * Ea[:, :2]


def _triangulate(xa, xb, R, t):
    """Rays' closest points: xa, xb (n, 2) normalised (already optimally corrected); returns
    (X in a (n, 3), depth_a, depth_b, angle rad)."""
    fa = np.c_[xa, np.ones(len(xa))]
    fb = np.c_[xb, np.ones(len(xb))]
    ra = fa @ R.T  # a's rays in b's frame
    # lambda_a ra + t = lambda_b fb  ->  least squares in (lambda_a, lambda_b)
    A11, A12, A22 = (ra * ra).sum(1), -(ra * fb).sum(1), (fb * fb).sum(1)
    b1, b2 = -(ra * t).sum(1), (fb * t).sum(1)
    det = A11 * A22 - A12 * A12
    with np.errstate(divide="ignore", invalid="ignore"):
        la = (A22 * b1 - A12 * b2) / det
        lb = (A11 * b2 - A12 * b1) / det
    X = fa * la[:, None]
    centre_b = -R.T @ t
    u = X / np.linalg.norm(X, axis=1, keepdims=True)
    v = X - centre_b
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    angle = np.arccos(np.clip((u * v).sum(1), -1, 1))
    return X, la, lb, angle


def two_view_geometry(fa: Features, fb: Features, K_a, K_b, opt: PairwiseOptions, va="a", vb="b", prior_E=None,
                      prior_px=None):
    """Verified matches, relative pose and triangulation of one pair, or None.

    ``prior_E`` (normalised coordinates, ``x_b^T E x_a = 0``): the putative matches are then
    searched within ``prior_px`` of its epipolar lines instead of the whole image (guided
    matching); the pose is still estimated from the images alone."""
    if len(fa.desc) < opt.min_inliers or len(fb.desc) < opt.min_inliers:
        return None
    if prior_E is None:
        S = fa.desc @ fb.desc.T  # RootSIFT: |a - b|^2 = 2 - 2 a.b
        ia, ib, r = _mutual_ratio(S, opt.ratio)
    else:
        # The similarities (one (n_a, n_b) product, ~40 ms at 4000 features) on a second thread while
        # the prior's epipolar band is searched (~30 ms): the same arrays, so the same matches.
        with ThreadPoolExecutor(1) as pool:
            S = pool.submit(np.matmul, fa.desc, fb.desc.T)
            i, j = guided_candidates(fa, fb, K_a, K_b, prior_E, prior_px)
            S = S.result()
        ia, ib, r = _sparse_mutual_ratio(i, j, S[i, j], opt.ratio)
    stats = {"putative": int(len(ia)), "robot_guided": prior_E is not None}
    if len(ia) < opt.min_inliers:
        return None
    na = cv2.undistortPoints(fa.uv[ia].reshape(-1, 1, 2), K_a, None).reshape(-1, 2)
    nb = cv2.undistortPoints(fb.uv[ib].reshape(-1, 1, 2), K_b, None).reshape(-1, 2)
    f = 0.5 * (K_a[0, 0] + K_b[0, 0])
    E, mask = cv2.findEssentialMat(na, nb, np.eye(3), cv2.USAC_ACCURATE, 0.9999, opt.ransac_px / f)
    if E is None or mask is None or E.shape != (3, 3):
        return None
    inl = mask.ravel().astype(bool)
    if inl.sum() < opt.min_inliers:
        return None
    _, R, t, pose_mask = cv2.recoverPose(E, na[inl], nb[inl], np.eye(3), mask=mask[inl].copy())
    t = t.ravel() / np.linalg.norm(t)
    E = skew(t) @ R
    if opt.guided:
        # Guided matching: the ratio test and the mutual check again, among the candidates
        # that lie within the inlier threshold of each other's epipolar lines.
        ia, ib, r = guided_matches(fa, fb, K_a, K_b, E, opt.ratio, 2 * opt.ransac_px, S)
        stats["guided"] = int(len(ia))
        if len(ia) < opt.min_inliers:
            return None
        na = cv2.undistortPoints(fa.uv[ia].reshape(-1, 1, 2), K_a, None).reshape(-1, 2)
        nb = cv2.undistortPoints(fb.uv[ib].reshape(-1, 1, 2), K_b, None).reshape(-1, 2)
        R, t = refine_pose(R, t, na, nb, opt.ransac_px / f)
        E = skew(t) @ R
        inl = np.ones(len(ia), bool)
    idx = np.flatnonzero(inl)
    # First-order optimal (Sampson) correction onto the final pose's epipolar geometry, then the rays meet.
    ca, cb = sampson_correction(E, na[idx], nb[idx])
    moved = np.maximum(np.linalg.norm((ca - na[idx]) * K_a[0, 0], axis=1),
                       np.linalg.norm((cb - nb[idx]) * K_b[0, 0], axis=1))
    X, da, db, angle = _triangulate(ca, cb, R, t)
    ok = np.isfinite(da) & np.isfinite(db) & (da > 0) & (db > 0) & (moved < opt.max_reprojection_px) & (angle > 0)
    idx = idx[ok]
    if len(idx) < opt.min_inliers:
        return None
    stats.update(inliers=int(len(idx)), median_angle_deg=float(np.degrees(np.median(angle[ok]))),
                 median_error_px=float(np.median(moved[ok])))
    return PairGeometry(va, vb, ia[idx], ib[idx], da[ok], db[ok], angle[ok], (1.0 - r[idx]).clip(0.05, 1.0),
                        R, t, stats)


def _homogeneous_rays(K, uv):
    return np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(K).T


def guided_matches(fa: Features, fb: Features, K_a, K_b, E, ratio, max_px, S=None):
    """Mutual ratio-test matches among the pairs within ``max_px`` of each other's epipolar line
    (``S``: the descriptor similarities, if already computed)."""
    i, j = guided_candidates(fa, fb, K_a, K_b, E, max_px)
    sim = S[i, j] if S is not None else np.einsum("nk,nk->n", fa.desc[i], fb.desc[j])
    return _sparse_mutual_ratio(i, j, sim, ratio)


def guided_candidates(fa: Features, fb: Features, K_a, K_b, E, max_px):
    """(i, j), row-major: the feature pairs within ``max_px`` of each other's epipolar line under E."""
    xa, xb = _homogeneous_rays(K_a, fa.uv), _homogeneous_rays(K_b, fb.uv)
    la = xa @ E.T  # epipolar lines in b of a's points (normalised coordinates)
    lb = xb @ E  # in a of b's points
    f = 0.5 * (K_a[0, 0] + K_b[0, 0])
    return _epipolar_candidates(la, lb, xb, f, max_px)


def _epipolar_candidates(la, lb, xb, f, max_px, rows=128):
    """(i, j), row-major: b's points within ``max_px`` of a's epipolar line (a few per mille of all
    pairs, tested on the float32 algebraic error x_b^T E x_a), then the same for b's line in a (float64,
    on that list). The dense test runs on ``rows`` of a's points at a time, so its (rows, n_b) block
    stays in cache: the same products (one matrix product of two or more rows per block, each entry
    the same length-3 dot product as in one (n_a, n_b) product; a lone row would be a matrix-vector
    product, summed otherwise, so the last block never has one row), the same list, about four times
    as fast as one product and a 2-d np.nonzero on a 4000-feature pair."""
    thr = (max_px / f * np.hypot(la[:, 0], la[:, 1])).astype(np.float32)
    thr *= thr
    la32, xbT32 = la.astype(np.float32), xb.T.astype(np.float32)
    hb = np.hypot(lb[:, 0], lb[:, 1])  # per point of b, gathered below
    bounds = list(range(0, len(la), rows)) + [len(la)]
    if len(bounds) > 2 and bounds[-1] - bounds[-2] == 1:
        bounds.pop(-2)
    out_i, out_j = [], []
    for r0, r1 in zip(bounds[:-1], bounds[1:]):
        alg = la32[r0:r1] @ xbT32  # x_b^T E x_a
        alg *= alg
        k = np.flatnonzero(alg < thr[r0:r1, None])  # a 2-d np.nonzero is ~4x slower
        i = k // alg.shape[1]
        j = k - i * alg.shape[1]
        e = np.einsum("nk,nk->n", xb[j], la[r0 + i])
        ok = np.abs(e) * f / hb[j] < max_px
        out_i.append(r0 + i[ok])
        out_j.append(j[ok])
    if not out_i:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    return np.concatenate(out_i), np.concatenate(out_j)


def _sparse_mutual_ratio(i, j, sim, ratio):
    """Mutual best matches passing the ratio test, among candidate pairs (i, j) with similarity sim.
    A lone candidate is compared with the largest possible distance (2). A row's best is its first
    candidate of the highest similarity, a column's likewise; computed by segment reductions over
    the rows (the candidates come row-major) and a stable sort of the columns, not two full lexsorts
    (a rescue's band holds ~300k candidates)."""
    if len(i) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    if np.any(i[1:] < i[:-1]):
        o = np.argsort(i, kind="stable")
        i, j, sim = i[o], j[o], sim[o]
    n = len(i)
    pos = np.arange(n)
    starts = np.flatnonzero(np.r_[True, i[1:] != i[:-1]])
    first, s1, rest = _segment_best(sim, starts, pos)
    s2 = np.full(len(s1), -1.0)
    has_second = np.diff(np.r_[starts, n]) > 1
    s2[has_second] = rest[has_second]
    bi, bj = i[first], j[first]
    r = np.sqrt(np.maximum(2 - 2 * s1, 0)) / np.maximum(np.sqrt(np.maximum(2 - 2 * s2, 0)), 1e-9)
    # mutual: the best a of each b
    o = np.argsort(j.astype(np.uint16) if j.max() < 2 ** 16 else j, kind="stable")  # uint16: a radix sort, 10x
    js = j[o]
    col_starts = np.flatnonzero(np.r_[True, js[1:] != js[:-1]])
    col_first, _, _ = _segment_best(sim[o], col_starts, pos, need_rest=False)
    best_a = np.full(j.max() + 1, -1)
    best_a[js[col_starts]] = i[o][col_first]
    keep = (best_a[bj] == bi) & (r < ratio)
    return bi[keep], bj[keep], r[keep]


def _segment_best(x, starts, pos, need_rest=True):
    """Per segment of ``x`` (segments begin at ``starts``): the position of its first maximum, the
    maximum, and the maximum of the other entries (-inf for a segment of one)."""
    top = np.maximum.reduceat(x, starts)
    seg = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(x)]))
    first = np.minimum.reduceat(np.where(x == top[seg], pos, len(x)), starts)
    if not need_rest:
        return first, top, None
    rest = x.copy()
    rest[first] = -np.inf
    return first, top, np.maximum.reduceat(rest, starts)


def refine_pose(R, t, xa, xb, thr):
    """(R, t) minimising the Sampson error of the matches (Huber, scale thr), |t| = 1."""
    from scipy.optimize import least_squares

    ha, hb = np.c_[xa, np.ones(len(xa))], np.c_[xb, np.ones(len(xb))]  # once, not per evaluation

    def res(p):
        Rk = cv2.Rodrigues(p[:3])[0] @ R
        tk = t + p[3:]
        tk = tk / np.linalg.norm(tk)
        E = skew(tk) @ Rk
        Ea, Eb = ha @ E.T, hb @ E
        num = (hb * Ea).sum(1)
        return num / np.sqrt(Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Eb[:, 0] ** 2 + Eb[:, 1] ** 2)

    sol = least_squares(res, np.zeros(6), loss="huber", f_scale=thr, x_scale=1e-3, max_nfev=50)
    Rk = cv2.Rodrigues(sol.x[:3])[0] @ R
    tk = t + sol.x[3:]
    return Rk, tk / np.linalg.norm(tk)


_PAIR_ARRAYS = ("ia", "ib", "depth_a", "depth_b", "angle", "conf", "R", "t")


def pair_geometries(ds, feats: dict, pairs, opt: PairwiseOptions, cache_dir=None, progress=True, workers=2) -> dict:
    """{(a, b): PairGeometry or None} for the given view pairs, from the cache where present."""
    cache = Path(cache_dir) / "pairs" if cache_dir else None
    K = {v: ds.cameras[split_view_id(v)[0]].K for v in feats}

    def one(ab):
        a, b = ab
        path = None
        if cache is not None:
            ca, fa_ = split_view_id(a)
            cb, fb_ = split_view_id(b)
            key = _digest([_image_key(ds, ds.cameras[ca], fa_), _image_key(ds, ds.cameras[cb], fb_), opt.pair_key()])
            path = cache / f"{ca}_{fa_}__{cb}_{fb_}_{key}.npz"
            if path.is_file():
                z = read_npz(path)
                if "none" in z:
                    return ab, None
                return ab, PairGeometry(a, b, *(z[k] for k in _PAIR_ARRAYS), json.loads(str(z["stats"])))
        g = two_view_geometry(feats[a], feats[b], K[a], K[b], opt, a, b)
        if path is not None:
            if g is None:
                atomic_savez(path, none=np.zeros(0))
            else:
                atomic_savez(path, **{k: getattr(g, k) for k in _PAIR_ARRAYS}, stats=json.dumps(g.stats))
        return ab, g

    return _map_with_progress(one, pairs, "pairwise: two-view geometry", progress, workers)
