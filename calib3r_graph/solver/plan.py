"""What recording one more robot pose would add to the calibration's graph, for the guide that ranks
candidate poses (solver/guidance.py: ``calib3r-graph live`` and ``calib3r-graph plan``).

For a candidate flange pose E (:func:`candidate_factors`) the current final graph is extended with what a new
recording would add: the reference camera's view at ``E * ee_T_cam`` with its robot pose
factor, and a 3D match factor to the existing view that sees most of the same scene, among the
views within the viewpoint change that the solution's own pairs span (:func:`matched_view_angle_deg`).
That factor's matches are the existing view's matched points re-projected into the
candidate (kept when in front of the camera and inside its image), whitened with the
same calibrated noise as the real scene factors. The guide scores that information's effect on the
total covariance (guidance.score_candidates).
"""

from dataclasses import dataclass

import gtsam
import numpy as np

import factors
from calib3r_graph.io.predictions import split_view_id
from calib3r_graph.solver.graph import point_sqrt_info
from factors.hand_eye import robot_pose_noise_covariance

MIN_VISIBLE = 30


def scene_points(sol, view):
    """Metric points (camera frame) of a view from every pair it takes part in."""
    pts = []
    for o in sol.observations:
        if o.view_a == view:
            pts.append(o.pts_a)
        elif o.view_b == view:
            pts.append(o.pts_b)
    return np.concatenate(pts) * sol.depth_scale[view] if pts else np.zeros((0, 3))


def scene_points_by_view(sol) -> dict:
    """{view: :func:`scene_points`} of the reference camera's views, computed once for many candidates."""
    ref = list(sol.ee_T_cam)[0]
    return {v: scene_points(sol, v) for v in sol.base_T_cam if split_view_id(v)[0] == ref}


def distinct_points(points: dict) -> dict:
    """{view: (its distinct scene points, how often each occurs)} of :func:`scene_points_by_view`'s
    points: a view's points repeat once per pair that matched the same keypoint (about 8000 points
    at 10 pairs on rwhe_kuka_1, a few distinct thousand), and equal points project alike, so the
    visible count is the sum of the counts of the distinct points seen."""
    out = {}
    for v, P in points.items():
        if not len(P):
            out[v] = (P, np.zeros(0, int))
            continue
        # np.unique(P, axis=0) sorts rows as structured records: half of a guidance pass on rwhe_kuka_1
        # (0.15 of 0.29 CPU s at 20 frames); a lexsort of the columns finds the same rows and counts
        Ps = P[np.lexsort(P.T[::-1])]
        first = np.r_[True, np.any(Ps[1:] != Ps[:-1], axis=1)]
        out[v] = (Ps[first], np.diff(np.r_[np.flatnonzero(first), len(Ps)]))
    return out


@dataclass
class StackedPoints:
    """:func:`distinct_points` of every view, stacked once per scoring in the base frame, so that a
    candidate counts what it sees of every view's points in one projection instead of one per view
    (4094 projections, 0.24 of a 0.68 CPU s scoring of 48 candidates at 30 frames of rwhe_kuka_1)."""

    views: list  # the views, in sol.base_T_cam's order
    P: np.ndarray  # (M, 3) the points in the base frame
    count: np.ndarray  # (M,) how often each occurs in its view
    view: np.ndarray  # (M,) index into ``views``
    camera: np.ndarray  # (M, 6) fx, fy, cx, cy, width, height of the point's view

    @classmethod
    def of(cls, sol, preds, distinct: dict) -> "StackedPoints":
        views = [v for v in sol.base_T_cam if v in distinct]
        parts, counts, index, cams = [], [], [], []
        for i, v in enumerate(views):
            U, n = distinct[v]
            T = sol.base_T_cam[v]
            parts.append(U @ T.rotation().matrix().T + T.translation() if len(U) else np.zeros((0, 3)))
            K, (h, w) = preds.views[v].K, preds.views[v].depth.shape
            counts.append(n)
            index.append(np.full(len(U), i))
            cams.append(np.tile([K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h], (len(U), 1)))
        cat = lambda x, shape: np.concatenate(x) if x else np.zeros(shape)  # noqa: E731
        return cls(views, cat(parts, (0, 3)), cat(counts, (0,)).astype(int), cat(index, (0,)).astype(int),
                   cat(cams, (0, 6)))

    def visible_counts(self, C: gtsam.Pose3) -> dict:
        """{view: how many of its points (with repeats) a camera at base_T_cam ``C`` would see}: in
        front of it by 5 cm and inside the view's image, projected with the view's intrinsics (as
        :func:`candidate_factors`' own test)."""
        Ci = C.inverse()
        Q = self.P @ Ci.rotation().matrix().T + Ci.translation()
        k = self.camera
        u = Q[:, 0] / np.maximum(Q[:, 2], 1e-9) * k[:, 0] + k[:, 2]
        v = Q[:, 1] / np.maximum(Q[:, 2], 1e-9) * k[:, 1] + k[:, 3]
        vis = (Q[:, 2] > 0.05) & (u >= 0) & (u < k[:, 4]) & (v >= 0) & (v < k[:, 5])
        n = np.bincount(self.view[vis], weights=self.count[vis], minlength=len(self.views))
        return {view: int(round(c)) for view, c in zip(self.views, n)}


def view_axes(sol) -> dict:
    """{view: its optical axis (unit z of ``base_T_cam``) in the base frame}, computed once for many
    candidates (each compares its own axis with every view's)."""
    return {v: T.rotation().matrix()[:, 2] for v, T in sol.base_T_cam.items()}


def axis_angle_deg(za: np.ndarray, zb: np.ndarray) -> float:
    """Angle (deg) between two unit optical axes given in one frame."""
    return float(np.degrees(np.arccos(np.clip(za @ zb, -1.0, 1.0))))


def matched_view_angle_deg(sol, axes=None) -> float:
    """The largest optical-axis angle (deg) between the two views of any of ``sol``'s verified pairs:
    the viewpoint change the frontend has shown that it matches on this scene (180 with no pairs).
    ``axes``: :func:`view_axes` of ``sol``, if already computed.

    A candidate's scene factor is predicted only with views within it (:func:`candidate_factors`):
    on tabb_ds1 the verified pairs span at most 13.8 deg (median 5, 427 pairs), and the guide's
    picks 16-33 deg from every view so far were predicted to match but matched nothing (docs/live-notes.md)."""
    axes = view_axes(sol) if axes is None else axes
    angles = [axis_angle_deg(axes[o.view_a], axes[o.view_b]) for o in sol.observations]
    return max(angles) if angles else 180.0


def candidate_factors(sol, preds, noise, E: gtsam.Pose3, rng, max_points=2000, keys_new=None, points=None,
                      max_angle_deg=None, axes=None, stacked=None):
    """What recording flange pose ``E`` would add to ``sol``'s graph: ([factors], new Values, the
    overlapping view or None, visible points). The reference camera's view at ``E * ee_T_cam``
    with its robot pose factor, and a 3D match factor to the existing view that sees most of the
    same scene (see the module's docstring), among the views whose optical axis is within
    ``max_angle_deg`` of the candidate's (:func:`matched_view_angle_deg` of ``sol`` when None).
    ``points``: :func:`scene_points_by_view` of ``sol``; ``stacked``: :class:`StackedPoints` of their
    :func:`distinct_points` (the same counts, on fewer points, in one projection); ``axes``:
    :func:`view_axes` of ``sol``."""
    from calib3r_graph.solver.observations import PairObservations

    keys, cameras = sol.keys, list(sol.ee_T_cam)
    ref_cam = cameras[0]
    X = sol.ee_T_cam[ref_cam]
    C = E.compose(X)
    k_pose, k_scale = keys_new or (gtsam.symbol("n", 0), gtsam.symbol("m", 0))
    values = gtsam.Values()
    cov = robot_pose_noise_covariance(X, np.radians(noise.robot_sigma_deg), noise.robot_sigma_mm * 1e-3)
    out = [factors.make_robot_pose_factor(E, [keys.hand_eye(ref_cam), k_pose], gtsam.noiseModel.Gaussian.Covariance(cov))]
    values.insert(k_pose, C)

    def seen(v, P):  # (visible, P, Q: in the candidate camera, uv)
        K, (h, w) = preds.views[v].K, preds.views[v].depth.shape
        Q = P @ C.between(sol.base_T_cam[v]).rotation().matrix().T + C.between(sol.base_T_cam[v]).translation()
        uv = Q[:, :2] / np.maximum(Q[:, 2:3], 1e-9) @ np.diag([K[0, 0], K[1, 1]]) + K[:2, 2]
        return (Q[:, 2] > 0.05) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h), P, Q, uv

    axes = view_axes(sol) if axes is None else axes
    if max_angle_deg is None:
        max_angle_deg = matched_view_angle_deg(sol, axes)
    c_axis = C.rotation().matrix()[:, 2]
    best, best_count = None, -1
    counts = stacked.visible_counts(C) if stacked is not None else None
    for v in sol.base_T_cam:
        if split_view_id(v)[0] != ref_cam or axis_angle_deg(axes[v], c_axis) > max_angle_deg:
            continue
        if counts is not None:
            count = counts.get(v, 0)
        else:
            P = points[v] if points is not None else scene_points(sol, v)
            count = int(seen(v, P)[0].sum()) if len(P) else 0
        if count > best_count:  # (a view with no points never wins: MIN_VISIBLE below)
            best, best_count = v, count
    best_pts = None if best is None else seen(best, points[best] if points is not None else scene_points(sol, best))
    n_vis = 0 if best_pts is None else int(best_pts[0].sum())
    if n_vis < MIN_VISIBLE:
        return out, values, None, n_vis
    vis, P, Q, uv = best_pts
    idx = np.flatnonzero(vis)
    idx = rng.choice(idx, min(len(idx), max_points), replace=False)
    s_near = sol.depth_scale[best]
    values.insert(k_scale, s_near)
    obs = PairObservations(best, "candidate", uv[idx], uv[idx], P[idx] / s_near, Q[idx] / s_near,
                           np.ones(len(idx)), np.zeros((len(idx), 0)), np.zeros((len(idx), 0)))
    K = preds.views[best].K
    W = point_sqrt_info(obs, K, K, sol.base_T_cam[best].between(C), 1.0, noise,
                        np.full(len(idx), sol.scene_weight_scale))
    out.append(factors.make_match3d_factor(factors.Match3DMeasurement(obs.pts_a, obs.pts_b, W),
                                           [keys.pose(best), k_pose, keys.scale(best), k_scale]))
    return out, values, best, n_vis
