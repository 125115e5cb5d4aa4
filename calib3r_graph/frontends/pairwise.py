"""Pairwise RGB frontend: two-view geometry per co-visible pair, aggregated per view.

No global mapper has to succeed: like a foundation model's pairwise pointmaps, every pair of
views stands on its own, and a view is usable as soon as one pair with it is.

1. **Features**, once per image: the image is undistorted onto a pinhole grid with the same
   K (as every frontend here), downscaled so its long side is at most ``max_side`` px for
   extraction, and described by RootSIFT (OpenCV SIFT, L1-normalised, square-rooted).
   Keypoints are scaled back to the full-resolution grid. Keypoints OpenCV duplicates for a
   second orientation share one ``kp_id`` (same location), so depths from different pairs
   meet at one pixel.
2. **Which pairs** (``frontends/pair_selection.py``): not every pair. Each view is matched with
   its ``partners`` best partners by a VLAD descriptor of its features and by the flanges'
   relative rotation and distance, plus a spanning tree that keeps the candidates connected; views
   the verified pairs leave weakly connected get their next partners (``more_rounds``). The pairs
   matched grow linearly with the views. ``partners=0`` matches every pair.
   **Two-view geometry**, once per chosen pair (:func:`two_view_geometry`): mutual nearest
   neighbours that pass the ratio test (0.8), essential-matrix RANSAC (OpenCV USAC, 1 px, on
   the calibrated rays) and the relative pose ``x_b = R x_a + t`` with ``|t| = 1``. Then a
   guided pass: the ratio test and the mutual check again, among the candidates within 2 px
   of each other's epipolar lines (a chessboard's look-alike corners defeat a whole-image
   ratio test, not one along a line), and the pose refined on those matches (Sampson error,
   Huber). The matches are moved onto the epipolar geometry (first-order optimal, Sampson)
   and triangulated; cheirality and a 2 px check. Each pair thus gives a sparse pointmap in
   both of its views, in its own unit: its baseline.
3. **The robot helps, never as ground truth** (:func:`robot_consistent`, :func:`rescue_pairs`).
   It only rejects pairs, or narrows where matches are searched; every pose, depth and scale
   written comes from the images.

   - The flange's relative rotation angle equals the camera's whatever the hand-eye rotation
     (rotation angles are invariant under conjugation): a pair whose two-view rotation angle
     differs by more than ``angle_tol_deg`` has a wrong essential matrix and is dropped.
   - A rough hand-eye rotation, by RANSAC over the pairs' rotation axes (AX = XB): pairs whose
     rotation is more than ``rotation_tol_deg`` from ``X^T R_ee X`` are dropped.
   - A rough hand-eye translation, by RANSAC over triples of pairs: pairs whose translation
     direction is more than ``translation_tol_deg`` from the predicted one are dropped.
   - Robot-guided matching for weakly connected views (fewer than ``rescue_below`` usable
     pairs): the rough hand-eye and the flange motion predict a failed or rejected pair's
     epipolar geometry, putative matches are searched within ``rescue_band_deg`` of it, and
     the pose is estimated from those matches as above; it must pass the same checks.
   - A pose that disagrees with its image (``frontends/pose_check.py``): a view most of
     whose pairs the robot rejects while its partners' other pairs pass is set aside, the others
     are checked again without it (a good view that failed only because of it is kept), and how
     far its pose is from what its images show (deg; mm where two good partners place its camera)
     is written to ``info.json`` (``pose_disagreements``, ``unusable_reasons``) and warned about.
4. **Per-pair scale, handled explicitly in the aggregation** (:func:`aggregate`). Every
   pair's triangulation is in its own unit (its baseline), so a view's pairwise depths differ
   by one unknown factor per pair. Per view, the reference is, of the three pairs with the most
   well-triangulated points, the one most other pairs agree with (a wrong geometry with many
   points must not set the unit); the other pairs are brought to its unit one by one, each by the
   weighted median of the log depth ratios on the keypoints it shares with the pairs
   already aligned (the pair sharing most goes first). A pair that shares fewer than
   ``min_shared`` keypoints, or whose ratios scatter by more than ``max_scale_mad`` (a wrong
   geometry), gives no depth to that view. Each view is then in one unit of its own; the
   graph's per-view depth scale ``s_v`` absorbs the unit, so no pair's scale is a variable.
5. **Aggregation (the paper's eq. 1)**: per keypoint ``d = sum_e C_e d_e / sum_e C_e`` over
   the pairs, with ``C_e`` from the triangulation angle (full at 5 degrees or more, as in
   the colmap frontend); entries more than ``max_depth_spread`` from the keypoint's
   weighted median are given no weight first. The conf written is eq. 1's mean of the
   ``C_e``. The depth is splatted onto the 2x2 pixels around each keypoint (conf 0
   elsewhere), so bilinear sampling at the keypoint returns it.
6. **Matches**: every verified pair's inlier matches, on a top-k co-visibility graph by the
   number of matches with depth at both ends; match confidence ``1 - distance ratio``.

A view with no usable pair is named in a warning, with its reason in ``info.json``'s
``unusable_reasons``, and left out; the rest go on.

Features and pair geometries can be cached on disk (``cache_dir``), keyed by the image file
and every parameter that changes them (a pair's geometry depends on its two images only, not
on which other pairs were chosen), so subsets of a recording only select pairs,
aggregate and solve (``bench/views_real.py``).
"""

import hashlib
import itertools
import json
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import gtsam
import numpy as np
from tqdm import tqdm

from factors._lie import skew
from calib3r_graph.errors import InputError, SolveError
from calib3r_graph.frontends.common import (FULL_CONF_ANGLE_DEG, aggregate_pointmaps, covisibility_edges, load_gray,
                                            undistort_maps)
from calib3r_graph.frontends.pair_selection import PairSelection
from calib3r_graph.frontends.pose_check import find_pose_disagreements
from calib3r_graph.geometry import hand_eye_rotation, rotation_angle_deg
from calib3r_graph.io.output import atomic_savez
from calib3r_graph.io.predictions import (PairMatches, Predictions, ViewPrediction, save_predictions, split_view_id,
                                          view_id)
from calib3r_graph.solver.observations import sample_bilinear

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PairwiseOptions:
    # features
    max_side: int = 1600  # long side of the image SIFT sees (px); keypoints are scaled back
    n_features: int = 4000
    contrast_threshold: float = 0.02  # OpenCV's default 0.04 is twice COLMAP's peak threshold
    # two-view geometry
    ratio: float = 0.8
    ransac_px: float = 1.0  # essential-matrix inlier threshold on the full-resolution grid
    min_inliers: int = 30
    max_reprojection_px: float = 2.0
    guided: bool = True  # second matching pass along the epipolar lines of the first pose
    # which pairs are matched (frontends/pair_selection.py): each view's best partners by the image
    # and the robot, 0 = every pair. 10 partners give each view more verified pairs than the 8
    # neighbours the matches keep (``neighbours``), after the pairs that do not verify.
    partners: int = 10
    more_rounds: int = 2  # rounds of further partners for weakly connected views
    # robot consistency (never ground truth: it only rejects pairs)
    angle_tol_deg: float = 1.0
    rotation_tol_deg: float = 1.0
    translation_tol_deg: float = 5.0
    rescue: bool = True  # robot-guided matching for the pairs of weakly connected views
    rescue_below: int = 6  # ... views with fewer usable pairs than this
    rescue_band_deg: float = 0.5  # half-width of the predicted epipolar band (angle at the camera)
    # aggregation
    min_pair_angle_deg: float = 0.5  # median triangulation angle below which a pair gives no depth
    min_shared: int = 8
    max_scale_mad: float = 0.05  # robust scatter (log) of a pair's depth ratios to the reference
    max_depth_spread: float = 0.05  # relative deviation from a keypoint's median depth
    min_view_points: int = 30
    neighbours: int = 8

    def feature_key(self) -> dict:
        return {"max_side": self.max_side, "n_features": self.n_features,
                "contrast_threshold": self.contrast_threshold, "v": 1}

    def pair_key(self) -> dict:
        # v3: pairs matched on the cache's float16 descriptors (extract_features); a v2 pair may have
        # been matched on the float32 ones of the run that made the cache
        return {"ratio": self.ratio, "ransac_px": self.ransac_px, "min_inliers": self.min_inliers,
                "max_reprojection_px": self.max_reprojection_px, "guided": self.guided, **self.feature_key(), "v": 3}


@dataclass
class Features:
    uv: np.ndarray  # (N, 2) float64, undistorted full-resolution pixels (OpenCV convention)
    desc: np.ndarray  # (N, 128) float32 RootSIFT, unit L2 norm
    kp_id: np.ndarray  # (N,) int: features at the same location share an id


@dataclass
class PairGeometry:
    view_a: str
    view_b: str
    ia: np.ndarray  # (n,) feature indices in a
    ib: np.ndarray  # (n,) feature indices in b
    depth_a: np.ndarray  # (n,) z in camera a, in the pair's unit (|t| = 1)
    depth_b: np.ndarray
    angle: np.ndarray  # (n,) triangulation angle, rad
    conf: np.ndarray  # (n,) 1 - distance ratio
    R: np.ndarray  # x_b = R x_a + t
    t: np.ndarray
    stats: dict = field(default_factory=dict)

    def __len__(self):
        return len(self.ia)


# ----------------------------------------------------------------------------- features


def _digest(obj) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _image_key(ds, cam, frame) -> dict:
    p = ds.image_path(cam.name, frame)
    st = p.stat()
    return {"image": str(p.resolve()), "size": st.st_size, "mtime": int(st.st_mtime), "params": list(cam.params),
            "w": cam.width, "h": cam.height}


def extract_features(ds, cam, frame, opt: PairwiseOptions) -> Features:
    gray = load_gray(ds.image_path(cam.name, frame))
    if gray.shape != (cam.height, cam.width):
        raise InputError(ds.image_path(cam.name, frame), f"image is {gray.shape[1]}x{gray.shape[0]}, camera "
                                                        f"{cam.name} is {cam.width}x{cam.height}")
    maps = undistort_maps(cam)
    if maps is not None:
        gray = cv2.remap(gray, *maps, cv2.INTER_LINEAR)
    s = min(1.0, opt.max_side / max(gray.shape))
    small = cv2.resize(gray, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s < 1 else gray
    sift = cv2.SIFT_create(nfeatures=opt.n_features, contrastThreshold=opt.contrast_threshold)
    kp, desc = sift.detectAndCompute(small, None)
    if desc is None or not kp:
        return Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32), np.zeros(0, np.int64))
    pts = np.array([k.pt for k in kp], dtype=np.float64)
    # small-image pixel centres -> full-resolution pixel centres (OpenCV: centre of pixel 0 at 0)
    uv = (pts + 0.5) / np.array([small.shape[1] / gray.shape[1], small.shape[0] / gray.shape[0]]) - 0.5
    desc = desc.astype(np.float32)
    desc /= np.maximum(desc.sum(1, keepdims=True), 1e-12)  # RootSIFT
    # at the precision the feature cache keeps (float16, features_for): a run that computes the
    # features and one that reads them back then match the same descriptors. Without it they differed
    # by up to 1.2e-4, and solve on tabb_ds1 from an empty cache and then from the cache by 0.49 sigma
    # (docs/frontends.md)
    desc = np.sqrt(desc).astype(np.float16).astype(np.float32)
    _, kp_id = np.unique(np.round(pts * 100).astype(np.int64), axis=0, return_inverse=True)
    return Features(uv, desc, kp_id.ravel())


def features_for(ds, views, opt: PairwiseOptions, cache_dir=None, progress=True, workers=2) -> dict:
    """{view: Features} for the given view ids, from the cache where present."""
    cache = Path(cache_dir) / "features" if cache_dir else None

    def one(vid):
        cam_name, frame = split_view_id(vid)
        cam = ds.cameras[cam_name]
        path = None
        if cache is not None:
            path = cache / f"{cam_name}_{frame}_{_digest([_image_key(ds, cam, frame), opt.feature_key()])}.npz"
            if path.is_file():
                with np.load(path) as z:
                    return vid, Features(z["uv"], z["desc"].astype(np.float32), z["kp_id"])
        f = extract_features(ds, cam, frame, opt)
        if path is not None:
            atomic_savez(path, uv=f.uv, desc=f.desc.astype(np.float16), kp_id=f.kp_id)
        return vid, f

    return _map_with_progress(one, views, "pairwise: features", progress, workers)


def _map_with_progress(one, items, desc, progress, workers) -> dict:
    """dict(one(item) for item in items), on ``workers`` threads, with a progress bar."""
    out = {}
    with ThreadPoolExecutor(max(1, workers)) as pool:
        for key, value in tqdm(pool.map(one, items), total=len(items), desc=desc,
                               disable=None if progress else True, leave=False):
            out[key] = value
    return out


# ----------------------------------------------------------------------------- two-view geometry


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
                with np.load(path) as z:
                    if "none" in z.files:
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


# ----------------------------------------------------------------------------- the robot's help


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
        na, nb = alphas / np.linalg.norm(alphas, axis=1, keepdims=True), betas / np.linalg.norm(betas, axis=1,
                                                                                                   keepdims=True)
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


# ----------------------------------------------------------------------------- aggregation


def _weighted_median(x, w):
    order = np.argsort(x)
    cw = np.cumsum(w[order])
    return x[order][np.searchsorted(cw, 0.5 * cw[-1])]


def _angle_conf(angle):
    return np.clip(angle / np.radians(FULL_CONF_ANGLE_DEG), 0.05, 1.0)


def _median_angle_deg(g: PairGeometry) -> float:
    """The pair's median triangulation angle (deg): ``two_view_geometry`` wrote exactly this number
    (``np.degrees(np.median(angle))`` of the angles it kept) into its stats; computed where absent."""
    m = g.stats.get("median_angle_deg")
    return float(np.degrees(np.median(g.angle))) if m is None else m


def view_depths(vid, feats: Features, geoms: dict, opt: PairwiseOptions):
    """Per-keypoint depth of one view from its pairs, every pair brought to one unit.

    Returns (kp ids (M,), depth (M,), conf (M,), {pair: log scale}) — the scale that maps the
    pair's unit to the view's — or None when no pair gives depth."""
    entries = []  # (pair, kp ids, depth, angle-conf)
    for ab, g in geoms.items():
        if vid not in ab or _median_angle_deg(g) < opt.min_pair_angle_deg:
            continue
        idx, d = (g.ia, g.depth_a) if ab[0] == vid else (g.ib, g.depth_b)
        entries.append((ab, feats.kp_id[idx], d, _angle_conf(g.angle)))
    if not entries:
        return None
    # Reference: of the three pairs with the most (angle-weighted) triangulated points, the one
    # the most other pairs agree with (a wrong geometry with many points must not set the unit).
    order = sorted(range(len(entries)), key=lambda k: -entries[k][3].sum())
    n_kp = int(feats.kp_id.max()) + 1 if len(feats.kp_id) else 0
    prep = _AlignInputs(entries, n_kp)
    best = None
    for ref in order[:3]:
        scales = _align(vid, entries, ref, order, n_kp, opt, prep)
        weight = sum(entries[k][3].sum() for k in range(len(entries)) if entries[k][0] in scales)
        if best is None or weight > best[0]:
            best = (weight, scales)
        if len(scales) == len(entries):
            break  # every pair aligned: no later reference can weigh more (a sum of fewer positive terms)
    scales = best[1]
    # Eq. 1 on the keypoints, after dropping entries far from each keypoint's weighted median.
    used = [k for k in range(len(entries)) if entries[k][0] in scales]
    ids_all = np.unique(np.concatenate([entries[k][1] for k in used]))
    P, M = len(used), len(ids_all)
    D = np.zeros((P, 1, M))
    C = np.zeros((P, 1, M))
    for p, k in enumerate(used):
        ab, ids, d, c = entries[k]
        j = np.searchsorted(ids_all, ids)
        o = np.argsort(c)  # the same keypoint twice in one pair (two orientations): the better one wins
        D[p, 0, j[o]] = d[o] * np.exp(scales[ab])
        C[p, 0, j[o]] = c[o]
    logD = np.log(np.where(D[:, 0] > 0, D[:, 0], 1.0))
    med = _weighted_median_columns(logD, C[:, 0])
    C[:, 0] = np.where(np.abs(logD - med[None]) > opt.max_depth_spread, 0.0, C[:, 0])
    depth, conf = aggregate_pointmaps(D, C)
    ok = depth[0] > 0
    return ids_all[ok], depth[0][ok].astype(np.float64), conf[0][ok].astype(np.float64), scales


class _AlignInputs:
    """What :func:`_align` reads of a view's entries, computed once for its three reference tries:
    each entry's log depths and its kp-id counts (P, n_kp), so that the keypoints each pending pair
    shares with those already aligned are one matrix-vector product, not one gather per pair and
    step."""

    def __init__(self, entries, n_kp):
        self.logd = [np.log(e[2]) for e in entries]
        self.counts = (np.array([np.bincount(e[1], minlength=n_kp) for e in entries], np.float64) if n_kp
                       else np.zeros((len(entries), 0)))


def _align(vid, entries, ref, order, n_kp, opt, prep=None):
    """{pair: log scale into ref's unit} of the pairs that agree with ``ref``, greedily: the pair
    sharing most keypoints with those already aligned goes next (ties: the earlier in ``order``)."""
    prep = prep or _AlignInputs(entries, n_kp)
    acc_w = np.zeros(n_kp)
    acc_logd = np.zeros(n_kp)
    scales = {}

    def add(k, log_s):
        ab, ids, d, c = entries[k]
        np.add.at(acc_w, ids, c)
        np.add.at(acc_logd, ids, c * (prep.logd[k] + log_s))
        scales[ab] = log_s

    add(ref, 0.0)
    pending = np.array([k for k in order if k != ref], int)  # in order: argmax's first maximum breaks ties
    while len(pending):
        shared = (prep.counts @ (acc_w > 0))[pending]
        at = int(np.argmax(shared))
        k = int(pending[at])
        pending = pending[pending != k]
        if shared[at] < opt.min_shared:
            break  # nothing left overlaps the aligned pairs
        ab, ids, d, c = entries[k]
        m = acc_w[ids] > 0
        im = ids[m]
        diff = acc_logd[im] / acc_w[im] - prep.logd[k][m]
        w = c[m] * np.minimum(acc_w[im], 1.0)
        log_s = _weighted_median(diff, w)
        mad = 1.4826 * _weighted_median(np.abs(diff - log_s), w)
        if mad > opt.max_scale_mad:
            log.debug("%s: pair %s-%s gives no depth (scale ratios scatter by %.1f %%)", vid, *ab, 100 * mad)
            continue
        add(k, log_s)
    return scales


def _weighted_median_columns(x, w):
    """Weighted median of each column of x (P, M) under weights w (P, M); zero weight = absent."""
    key = np.where(w > 0, x, np.inf)
    order = np.argsort(key, axis=0)
    xs, ws = np.take_along_axis(key, order, 0), np.take_along_axis(w, order, 0)
    cw = np.cumsum(ws, axis=0)
    k = np.argmax(cw >= 0.5 * cw[-1:], axis=0)
    return xs[k, np.arange(x.shape[1])]


def _unchanged_view(hit, feats: Features, res):
    """(ViewPrediction, info) of the last aggregation of this view where ``res`` (view_depths' result,
    its pairs having changed) gives the same keypoints, depths and confidences: the depth maps would
    be the same arrays, so the same object is kept (no new maps, no re-sampled matches). Else None."""
    if hit is None or hit[0] is not feats or hit[3] is None or hit[2] is None or res is None:
        return None
    if not all(x.shape == y.shape and np.array_equal(x, y) for x, y in zip(hit[2][:3], res[:3])):
        return None
    view, view_info = hit[3]
    return view, (view_info if view_info["pairs"] == len(res[3]) else {**view_info, "pairs": len(res[3])})


def _still_growing(hit, feats: Features, mine, regrow) -> bool:
    """Whether a view's last aggregation (``hit``: aggregate's cache entry) stands for its pairs
    ``mine`` under ``regrow``: the same features, a usable result, each pair it came from still there
    with the same geometry, and fewer than ``regrow`` times as many pairs now."""
    if hit is None or hit[0] is not feats or hit[2] is None or hit[3] is None or len(mine) >= regrow * len(hit[1]):
        return False
    now = dict(mine)
    return all(now.get(ab) is g for ab, g in hit[1])


def _pair_end(cache, ab, end, g, feats: Features, view):
    """One end of a pair's match check: its matches' pixels, whether the view's depth map has depth
    there (all four neighbours), and the log ratio of that depth to the pair's own. Kept while the
    pair's geometry and that view's prediction are the same objects: a new depth map at one end
    re-samples only that end."""
    key = ("end", *ab, end)
    hit = cache.get(key)
    if hit is not None and hit[0] is g and hit[1] is view:
        return hit[2]
    uv = feats.uv[g.ia if end == 0 else g.ib]
    d, ok = sample_bilinear(view.depth, uv)
    with np.errstate(divide="ignore", invalid="ignore"):
        lr = np.log(d) - np.log(g.depth_a if end == 0 else g.depth_b)
    cache[key] = (g, view, (uv, ok, lr))
    return cache[key][2]


def aggregate(ds, feats: dict, geoms: dict, opt: PairwiseOptions, known_reasons: dict | None = None,
              cache: dict | None = None, regrow: float | None = None):
    """(views {vid: ViewPrediction}, pairs [PairMatches], info) from verified pair geometries.
    ``info["reasons"]`` says in one line why each of ``info["unusable"]`` is left out;
    ``known_reasons`` are the views already explained (and warned about) by the caller.

    ``cache`` (a dict the caller keeps, e.g. a live session adding frames): a view whose features and
    pair geometries (the same objects, in the same order) are those of the last call is not
    aggregated again, and a pair whose geometry and both views are unchanged keeps its matches;
    the results are the same objects as before, so a caller can tell what changed by identity. A
    view whose pairs changed but whose keypoint depths come out the same keeps its prediction too,
    and a pair re-samples only the end whose prediction is new.

    ``regrow`` (with ``cache``): a view keeps its last aggregation while every pair it was aggregated
    from is still there, unchanged, and it has fewer than ``regrow`` times as many pairs; a new pair's
    matches then meet the depth that view had (a live session: ``live/sources.py`` says why)."""
    known_reasons = known_reasons or {}
    cache = {} if cache is None else cache
    views, info = {}, {"views": {}, "unusable": [], "reasons": {}}
    for vid in sorted(feats):
        cam = ds.cameras[split_view_id(vid)[0]]
        mine = [(ab, g) for ab, g in geoms.items() if vid in ab]
        hit = cache.get(("view", vid))
        if hit is not None and hit[0] is feats[vid] and len(hit[1]) == len(mine) and all(
                ab == ab2 and g is g2 for (ab, g), (ab2, g2) in zip(hit[1], mine)):
            res, done = hit[2], hit[3]
        elif regrow and _still_growing(hit, feats[vid], mine, regrow):
            res, done = hit[2], hit[3]  # (the cache keeps the pairs it was aggregated from)
        else:  # view_depths reads only the view's own pairs, in geoms' order
            res = view_depths(vid, feats[vid], dict(mine), opt)
            done = _unchanged_view(hit, feats[vid], res)
            cache[("view", vid)] = (feats[vid], mine, res, done)
        if res is None or len(res[0]) < opt.min_view_points:
            n = 0 if res is None else len(res[0])
            info["unusable"].append(vid)
            if vid in known_reasons:
                info["reasons"][vid] = known_reasons[vid]
                continue
            n_pairs = sum(vid in ab for ab in geoms)
            info["reasons"][vid] = (f"no usable two-view geometry ({n_pairs} verified pair(s) agree with the robot's "
                                    f"motion, {n} triangulated points)")
            log.warning("view %s: %s; left out of the predictions, the others go on", vid, info["reasons"][vid])
            continue
        if done is not None:
            views[vid], info["views"][vid] = done
            continue
        ids, depth_kp, conf_kp, scales = res
        # one feature per kp id: its (full-resolution) location
        first = np.full(int(feats[vid].kp_id.max()) + 1, -1)
        first[feats[vid].kp_id[::-1]] = np.arange(len(feats[vid].kp_id))[::-1]
        uv = feats[vid].uv[first[ids]]
        depth = np.zeros((cam.height, cam.width), np.float32)
        conf = np.zeros((cam.height, cam.width), np.float32)  # zeros, not zeros_like: untouched pages stay unwritten
        x0, y0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (x0 >= 0) & (y0 >= 0) & (x0 < cam.width - 1) & (y0 < cam.height - 1)
        order = np.argsort(conf_kp[ok])  # where splats overlap, the most confident one wins
        at = y0[ok][order] * cam.width + x0[ok][order]  # flat pixel index, written in the same order
        d_kp, c_kp = depth_kp[ok][order], conf_kp[ok][order]
        for dx in (0, 1):
            for dy in (0, 1):
                depth.ravel()[at + (dy * cam.width + dx)] = d_kp
                conf.ravel()[at + (dy * cam.width + dx)] = c_kp
        views[vid] = ViewPrediction(depth, conf, cam.K)
        info["views"][vid] = {"points": int(ok.sum()), "pairs": len(scales)}
        cache[("view", vid)] = cache[("view", vid)][:3] + ((views[vid], info["views"][vid]),)
    # Matches: every verified pair's, where the depths written at both ends agree with the pair's
    # own triangulation up to one scale per end (a match along a repeated texture's epipolar
    # line, or a splat a neighbouring keypoint overwrote, does not); scored by how many do.
    cand, scores = {}, {}
    for (a, b), g in geoms.items():
        if a not in views or b not in views:
            continue
        hit = cache.get(("pair", a, b))
        if hit is not None and hit[0] is g and hit[1] is views[a] and hit[2] is views[b]:
            if hit[3] is not None:
                cand[(a, b)], scores[(a, b)] = hit[3], len(hit[3].conf)
            continue
        cache[("pair", a, b)] = (g, views[a], views[b], None)
        uv_a, ok_a, la = _pair_end(cache, (a, b), 0, g, feats[a], views[a])
        uv_b, ok_b, lb = _pair_end(cache, (a, b), 1, g, feats[b], views[b])
        ok = ok_a & ok_b
        if ok.sum() < 20:
            continue
        keep = ok.copy()
        keep[ok] = ((np.abs(la[ok] - np.median(la[ok])) < opt.max_depth_spread)
                    & (np.abs(lb[ok] - np.median(lb[ok])) < opt.max_depth_spread))
        if keep.sum() >= 20:
            cand[(a, b)] = PairMatches(a, b, uv_a[keep], uv_b[keep], g.conf[keep])
            scores[(a, b)] = int(keep.sum())
            cache[("pair", a, b)] = (g, views[a], views[b], cand[(a, b)])
    edges = covisibility_edges(scores, sorted(views), opt.neighbours)

    def flipped(e):
        c, hit = cand[e[::-1]], cache.get(("flipped", *e))
        if hit is None or hit[0] is not c:
            hit = cache[("flipped", *e)] = (c, PairMatches(e[0], e[1], c.uv_b, c.uv_a, c.conf))
        return hit[1]

    pairs = [cand[e] if e in cand else flipped(e) for e in edges]
    for vid in sorted(views):
        if not any(vid in (p.view_a, p.view_b) for p in pairs):
            info["unusable"].append(vid)
            info["reasons"][vid] = "its depth is shared with no other view"
            log.warning("view %s: its depth is shared with no other view; left out of the predictions", vid)
    used = {v for p in pairs for v in (p.view_a, p.view_b)}
    views = {v: p for v, p in views.items() if v in used}
    return views, pairs, info


# ----------------------------------------------------------------------------- the frontend


def _view_ids(ds, frames=None):
    frames = ds.frames if frames is None else [f for f in ds.frames if f in set(frames)]
    out = [view_id(c.name, f) for c in ds.cameras.values() for f in frames if ds.image_path(c.name, f)]
    if not out:
        raise InputError(ds.root / "images", "no images for the frames in robot_poses.csv")
    return out


def match_noise_px(kept: dict) -> float:
    """The predictions' match noise (px) from the kept pairs: 1.5 x the median Sampson error (the
    median Hartley-Sturm correction ~ 0.67 sigma of the larger of two 2D offsets), floor 0.5 px."""
    noise = [g.stats["median_error_px"] for g in kept.values() if "median_error_px" in g.stats]
    return float(max(0.5, 1.5 * np.median(noise))) if noise else 1.0


def pairwise_predictions(ds, frames=None, opt: PairwiseOptions | None = None, cache_dir=None, progress=True,
                         workers=2, name="pairwise") -> Predictions:
    """Predictions of the given frames (all if None), in memory."""
    opt = opt or PairwiseOptions()
    t0 = time.perf_counter()
    vids = _view_ids(ds, frames)
    feats = features_for(ds, vids, opt, cache_dir, progress, workers)
    t1 = time.perf_counter()
    selection = PairSelection(vids, {v: f.desc for v, f in feats.items()}, ds.base_T_ee, opt.partners)
    geoms = pair_geometries(ds, feats, selection.first(), opt, cache_dir, progress, workers)
    verified = {ab: g for ab, g in geoms.items() if g is not None}
    kept, robot_info = robot_consistent(verified, ds.base_T_ee, opt)
    rounds = [len(geoms)]
    for _ in range(opt.more_rounds):
        more = selection.more(geoms, kept, opt.rescue_below)
        if not more:
            break
        geoms.update(pair_geometries(ds, feats, more, opt, cache_dir, progress, workers))
        rounds.append(len(more))
        verified = {ab: g for ab, g in geoms.items() if g is not None}
        kept, robot_info = robot_consistent(verified, ds.base_T_ee, opt)
    t2 = time.perf_counter()
    kept_pd, info_pd, disagreements, reasons = find_pose_disagreements(verified, kept, ds.base_T_ee, opt,
                                                                        robot_consistent)
    if info_pd is not None:
        kept, robot_info = kept_pd, info_pd
    bad = {d["view"] for d in disagreements}
    good = {ab: g for ab, g in verified.items() if not set(ab) & bad}
    tried = [ab for ab in geoms if not set(ab) & bad]
    rescued = rescue_pairs(ds, feats, tried, kept, robot_info, opt, progress, workers) if opt.rescue else {}
    if rescued:
        kept, robot_info = robot_consistent({**good, **rescued}, ds.base_T_ee, opt)
    views, pairs, agg_info = aggregate(ds, feats, kept, opt, reasons)
    if not pairs:
        raise SolveError(f"pairwise: no two of the {len(vids)} images share enough verified, triangulated "
                         "matches (too little texture or overlap)")
    t3 = time.perf_counter()
    info = {"source": "calib3r-graph pairwise (OpenCV RootSIFT, essential-matrix RANSAC per pair, triangulation, "
                      "per-view scale alignment and eq. 1 aggregation)",
            "metric_depth": False,
            "match_noise_px": match_noise_px(kept),
            "images": len(vids), "views": len(views), "pairs": len(pairs), "verified_pairs": len(verified),
            "pairs_matched": len(geoms), "pairs_possible": len(vids) * (len(vids) - 1) // 2,
            "pairs_matched_per_round": rounds,
            "robot_consistent_pairs": len(kept), "robot_guided_pairs": len(set(rescued) & set(kept)),
            "unusable_views": agg_info["unusable"],
            "unusable_reasons": agg_info["reasons"],
            "pose_disagreements": disagreements,
            "rejected_by_robot_motion": robot_info["angle_rejected"] + robot_info["rotation_rejected"]
            + robot_info["translation_rejected"],
            "seconds": {"features": t1 - t0, "pairs": t2 - t1, "aggregation": t3 - t2},
            "options": asdict(opt)}
    log.info("pairwise frontend: %d/%d views, %d pairs (%d of %d matched, %d verified, %d robot-consistent), %.1f s",
             len(views), len(vids), len(pairs), len(geoms), len(vids) * (len(vids) - 1) // 2, len(verified), len(kept),
             t3 - t0)
    return Predictions(name, info, views, pairs)


def predict_pairwise(ds, name="pairwise", progress=True, cache_dir=None, workers=2, **kw) -> str:
    """Run the frontend on the whole dataset and write ``predictions/<name>/``."""
    opt = PairwiseOptions(**kw)
    preds = pairwise_predictions(ds, None, opt, cache_dir, progress, workers, name)
    save_predictions(ds.root, name, preds.views, preds.pairs, preds.info)
    return name
