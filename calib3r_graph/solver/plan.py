"""Next best pose: rank candidate robot poses by how much recording them would shrink the
calibration's uncertainty (expected information gain, at the current solution).

For each candidate flange pose E the current final graph is extended with what a new
recording would add: the reference camera's view at ``E * ee_T_cam`` with its robot pose
factor, and a 3D match factor to the existing view that sees most of the same scene.
That factor's matches are the existing view's matched points re-projected into the
candidate (kept when in front of the camera and inside its image), whitened with the
same calibrated noise as the real scene factors. The gain is

    IG = 1/2 sum_j log( det Sigma_j(before) / det Sigma_j(after) )      (nats)

over every camera's ee_T_cam marginal.
"""

from dataclasses import dataclass

import gtsam
import numpy as np

import factors
from calib3r_graph.io.predictions import split_view_id
from calib3r_graph.solver.graph import point_sqrt_info
from factors.hand_eye import robot_pose_noise_covariance

MIN_VISIBLE = 30


@dataclass
class CandidateScore:
    frame: str
    information_gain_nats: float
    sigma_t_mm_after: float  # largest translation sigma over cameras, ee frame
    sigma_r_deg_after: float
    overlapping_view: str | None
    visible_points: int


def largest_sigmas(covs) -> tuple[float, float]:
    """Largest translation sigma (mm) and rotation sigma (deg) over ee_T_cam covariances."""
    t = max(np.sqrt(np.linalg.eigvalsh(c[3:, 3:])[-1]) for c in covs) * 1e3
    r = max(np.sqrt(np.linalg.eigvalsh(c[:3, :3])[-1]) for c in covs)
    return float(t), float(np.degrees(r))


def _scene_points(sol, view):
    """Metric points (camera frame) of a view from every pair it takes part in."""
    pts = []
    for o in sol.observations:
        if o.view_a == view:
            pts.append(o.pts_a)
        elif o.view_b == view:
            pts.append(o.pts_b)
    return np.concatenate(pts) * sol.depth_scale[view] if pts else np.zeros((0, 3))


def rank_candidates(ds, preds, sol, noise, candidates: dict, max_points=2000) -> list:
    keys, cameras = sol.keys, list(sol.ee_T_cam)
    ref_cam = cameras[0]
    X = sol.ee_T_cam[ref_cam]
    # The same graph's marginals before and after: the noise model's covariance (the systematic
    # part does not shrink with one more pose of the same arm).
    before = [np.asarray(sol.covariance_model.get(c, sol.covariance[c])) for c in cameras]
    logdet_before = sum(np.linalg.slogdet(c)[1] for c in before)
    ref_views = [v for v in sol.base_T_cam if split_view_id(v)[0] == ref_cam]
    rng = np.random.default_rng(0)
    out = []
    for frame, E in candidates.items():
        C = E.compose(X)
        graph = gtsam.NonlinearFactorGraph(sol.graph)
        values = gtsam.Values(sol.values)
        k_pose, k_scale = gtsam.symbol("n", 0), gtsam.symbol("m", 0)
        cov = robot_pose_noise_covariance(X, np.radians(noise.robot_sigma_deg), noise.robot_sigma_mm * 1e-3)
        graph.add(factors.make_robot_pose_factor(E, [keys.hand_eye(ref_cam), k_pose],
                                                 gtsam.noiseModel.Gaussian.Covariance(cov)))
        values.insert(k_pose, C)
        # The existing view that sees most of what the candidate would see.
        best, best_pts = None, None
        for v in ref_views:
            P = _scene_points(sol, v)
            if len(P) == 0:
                continue
            K, (h, w) = preds.views[v].K, preds.views[v].depth.shape
            Q = P @ C.between(sol.base_T_cam[v]).rotation().matrix().T + C.between(sol.base_T_cam[v]).translation()
            uv = Q[:, :2] / np.maximum(Q[:, 2:3], 1e-9) @ np.diag([K[0, 0], K[1, 1]]) + K[:2, 2]
            vis = (Q[:, 2] > 0.05) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            if best_pts is None or vis.sum() > best_pts[0].sum():
                best, best_pts = v, (vis, P, Q, uv)
        n_vis = 0 if best_pts is None else int(best_pts[0].sum())
        if n_vis >= MIN_VISIBLE:
            vis, P, Q, uv = best_pts
            idx = np.flatnonzero(vis)
            idx = rng.choice(idx, min(len(idx), max_points), replace=False)
            s_near = sol.depth_scale[best]
            values.insert(k_scale, s_near)
            from calib3r_graph.solver.observations import PairObservations

            obs = PairObservations(best, "candidate", uv[idx], uv[idx], P[idx] / s_near, Q[idx] / s_near,
                                   np.ones(len(idx)), np.zeros((len(idx), 0)), np.zeros((len(idx), 0)))
            K = preds.views[best].K
            W = point_sqrt_info(obs, K, K, sol.base_T_cam[best].between(C), 1.0, noise,
                                np.full(len(idx), sol.scene_weight_scale))
            graph.add(factors.make_match3d_factor(factors.Match3DMeasurement(obs.pts_a, obs.pts_b, W),
                                                  [keys.pose(best), k_pose, keys.scale(best), k_scale]))
        marg = gtsam.Marginals(graph, values)
        after = [marg.marginalCovariance(keys.hand_eye(c)) for c in cameras]
        gain = 0.5 * (logdet_before - sum(np.linalg.slogdet(c)[1] for c in after))
        t_mm, r_deg = largest_sigmas(after)
        out.append(CandidateScore(frame, float(gain), t_mm, r_deg, best if n_vis >= MIN_VISIBLE else None, n_vis))
    return sorted(out, key=lambda c: -c.information_gain_nats)
