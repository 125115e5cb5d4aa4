"""The numbers behind the report, computed from a :class:`~calib3r_graph.solver.solve.Solution`.

* Per robot pose: the robot pose factor's residual ``e = Log((base_T_ee X)^-1 base_T_cam)`` on the
  frame's reference view (the first camera with a view at that frame, as in the graph), in mm and
  degrees, and its chi2 (6 dof) under the robot noise the solver calibrated
  (``stats.noise_calibration.robot_sigma_used``). Poses above the 99 % quantile of chi2(6) are
  flagged.
* Per view pair: matches, inliers (the solver's IRLS rule at the solution: Mahalanobis distance
  under the nominal per-match noise, robust scale, within the 99.9 % chi2(3) cut) and the median
  metric residual of the inliers in mm.
"""

import gtsam
import numpy as np

from calib3r_graph.io.predictions import split_view_id
from calib3r_graph.solver.graph import NoiseOptions, match_residuals, point_sqrt_info
from calib3r_graph.solver.solve import robust_weights
from factors.hand_eye import robot_pose_noise_covariance

CHI2_6_99 = 16.811893829770927  # scipy.stats.chi2.ppf(0.99, 6), written out: scipy.stats costs ~0.4 s to import


def robot_pose_residuals(sol, base_T_ee: dict) -> list:
    """One row per frame: reference view, residual (rotation deg, translation mm, both (3,) and
    norms), chi2 and whether it is above the 99 % quantile of chi2(6)."""
    sigma_mm, sigma_deg = sol.stats["noise_calibration"]["robot_sigma_used"]
    cameras = list(sol.ee_T_cam)
    by_frame = {}
    for v in sol.base_T_cam:
        by_frame.setdefault(split_view_id(v)[1], []).append(v)
    rows = []
    for frame in sorted(by_frame):
        ref = min(by_frame[frame], key=lambda v: cameras.index(split_view_id(v)[0]))
        X = sol.ee_T_cam[split_view_id(ref)[0]]
        e = gtsam.Pose3.Logmap(base_T_ee[frame].compose(X).between(sol.base_T_cam[ref]))
        cov = robot_pose_noise_covariance(X, np.radians(sigma_deg), sigma_mm * 1e-3)
        chi2 = float(e @ np.linalg.solve(cov, e))
        rows.append({"frame": frame, "view": ref, "rotation_deg": np.degrees(e[:3]).tolist(),
                     "translation_mm": (e[3:] * 1e3).tolist(),
                     "rotation_norm_deg": float(np.degrees(np.linalg.norm(e[:3]))),
                     "translation_norm_mm": float(np.linalg.norm(e[3:]) * 1e3), "chi2": chi2,
                     "flagged": chi2 > CHI2_6_99})
    return rows


def pair_statistics(sol, preds, noise: NoiseOptions | None = None) -> list:
    """One row per view pair the solver used: matches, inliers, median inlier residual (mm)."""
    obs = sol.observations
    if not obs or sol.values is None:
        return []
    noise = noise or NoiseOptions()
    values, keys = sol.values, sol.keys
    residuals = match_residuals(obs, values, keys)
    whitening = []
    for o in obs:
        T_a, T_b = values.atPose3(keys.pose(o.view_a)), values.atPose3(keys.pose(o.view_b))
        s_a, s_b = values.atDouble(keys.scale(o.view_a)), values.atDouble(keys.scale(o.view_b))
        whitening.append(point_sqrt_info(o, preds.views[o.view_a].K, preds.views[o.view_b].K, T_a.between(T_b),
                                         s_b / s_a, noise, np.ones(len(o))))
    weights = robust_weights(obs, residuals, whitening, [o.weight for o in obs])
    rows = []
    for o, e, w in zip(obs, residuals, weights):
        inl = w > 0
        r_mm = np.linalg.norm(e, axis=1) * values.atDouble(keys.scale(o.view_a)) * 1e3  # metres per unit of view a
        rows.append({"view_a": o.view_a, "view_b": o.view_b, "matches": int(len(o)), "inliers": int(inl.sum()),
                     "median_residual_mm": float(np.median(r_mm[inl])) if inl.any() else float("nan")})
    return rows
