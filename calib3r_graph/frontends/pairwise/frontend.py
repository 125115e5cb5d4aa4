"""Pairwise RGB frontend: two-view geometry per co-visible pair, aggregated per view.

No global mapper has to succeed: like a foundation model's pairwise pointmaps, every pair of
views stands on its own, and a view is usable as soon as one pair with it is.

1. **Features**, once per image (``features.py``): the image is undistorted onto a pinhole grid with the same
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
   **Two-view geometry**, once per chosen pair (``geometry.py``: :func:`two_view_geometry`): mutual nearest
   neighbours that pass the ratio test (0.8), essential-matrix RANSAC (OpenCV USAC, 1 px, on
   the calibrated rays) and the relative pose ``x_b = R x_a + t`` with ``|t| = 1``. Then a
   guided pass: the ratio test and the mutual check again, among the candidates within 2 px
   of each other's epipolar lines (a chessboard's look-alike corners defeat a whole-image
   ratio test, not one along a line), and the pose refined on those matches (Sampson error,
   Huber). The matches are moved onto the epipolar geometry (first-order optimal, Sampson)
   and triangulated; cheirality and a 2 px check. Each pair thus gives a sparse pointmap in
   both of its views, in its own unit: its baseline.
3. **The robot helps, never as ground truth** (``robot.py``: :func:`robot_consistent`, :func:`rescue_pairs`).
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
4. **Per-pair scale, handled explicitly in the aggregation** (``aggregation.py``: :func:`aggregate`). Every
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

import logging
import time
from dataclasses import asdict

import numpy as np

from calib3r_graph.errors import InputError, SolveError
from calib3r_graph.frontends.pair_selection import PairSelection
from calib3r_graph.frontends.pairwise.aggregation import aggregate
from calib3r_graph.frontends.pairwise.features import features_for
from calib3r_graph.frontends.pairwise.geometry import pair_geometries
from calib3r_graph.frontends.pairwise.options import PairwiseOptions
from calib3r_graph.frontends.pairwise.robot import rescue_pairs, robot_consistent
from calib3r_graph.frontends.pose_check import find_pose_disagreements
from calib3r_graph.io.predictions import Predictions, save_predictions, view_id

log = logging.getLogger(__name__)


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
