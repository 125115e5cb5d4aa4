"""3D match between the back-projected matched pixels of a view pair (Calib3R eq. 4).

For each match p of the view pair (a, b) the two predicted depths are lifted to
3D points in their cameras,

    P_a = s_a * d_a(p) * ray_a(p),      P_b = s_b * d_b(p) * ray_b(p),

with ``ray = K^-1 [u, v, 1]`` (z = 1), ``d`` the frontend's depth and ``s`` the
view's depth scale (metres per frontend unit). The residual compares them in
camera a's frame and is normalised by ``s_a``:

    e_p = (P_a - a_T_b * P_b) / s_a,      a_T_b = base_T_a^-1 * base_T_b,
    r_p = W_p e_p                                              (3 rows per match)

Dividing by ``s_a`` makes the residual invariant to a global change of scale,
so the scene factors carry no pull towards a smaller reconstruction (a plain
metric residual rewards shrinking it and biases the metric scale). ``W_p`` is a
fixed (3, 3) square-root information in the unit of view a's frontend depth:
per-point covariance from pixel and depth noise, confidence and robust weight,
built by the caller. Error dimension: 3N, dimensionless after whitening.

Keys: ``[base_T_a (Pose3), base_T_b (Pose3), s_a (double), s_b (double)]``.
"""

from dataclasses import dataclass
from functools import partial

import gtsam
import numpy as np

from factors._lie import skew, whiten_rows


@dataclass(frozen=True)
class Match3DMeasurement:
    """Everything a 3D match factor needs about one view pair; N matches."""

    ray_depth_a: np.ndarray  # (N, 3) d_a * ray_a: point in cam a at unit depth scale
    ray_depth_b: np.ndarray  # (N, 3) d_b * ray_b
    sqrt_info: np.ndarray  # (N, 3, 3) W_p, applied to e_p

    def __post_init__(self):
        n = len(self.ray_depth_a)
        assert self.ray_depth_a.shape == (n, 3) and self.ray_depth_b.shape == (n, 3)
        assert self.sqrt_info.shape == (n, 3, 3)

    @property
    def dim(self) -> int:
        return 3 * len(self.ray_depth_a)


def match3d_residuals(m: Match3DMeasurement, base_T_a: gtsam.Pose3, base_T_b: gtsam.Pose3,
                      s_a: float, s_b: float) -> np.ndarray:
    """Unwhitened per-match residuals e_p (N, 3) in view a's frontend-depth unit."""
    a_T_b = base_T_a.between(base_T_b)
    Q = (s_b * m.ray_depth_b) @ a_T_b.rotation().matrix().T + a_T_b.translation()
    return m.ray_depth_a - Q / s_a


def match3d_error(m: Match3DMeasurement, this: gtsam.CustomFactor, values: gtsam.Values,
                  jacobians) -> np.ndarray:
    k_a, k_b, k_sa, k_sb = this.keys()
    base_T_a, base_T_b = values.atPose3(k_a), values.atPose3(k_b)
    s_a, s_b = values.atDouble(k_sa), values.atDouble(k_sb)
    a_T_b = base_T_a.between(base_T_b)
    R_ab = a_T_b.rotation().matrix()
    P_b = s_b * m.ray_depth_b
    Q = P_b @ R_ab.T + a_T_b.translation()
    e = m.ray_depth_a - Q / s_a
    if jacobians is not None:
        n = len(Q)
        eye = np.broadcast_to(np.eye(3), (n, 3, 3))
        # d Q / d xi_a = [[Q]x, -I]  ->  d e / d xi_a = [-[Q]x, I] / s_a
        J_a = np.concatenate([-skew(Q), eye], axis=2) / s_a
        # d Q / d xi_b = [-R_ab [P_b]x, R_ab]  ->  d e / d xi_b = -(...) / s_a
        J_b = np.concatenate([R_ab @ skew(P_b), -np.broadcast_to(R_ab, (n, 3, 3))], axis=2) / s_a
        J_sa = (Q / s_a**2)[:, :, None]
        J_sb = (-(m.ray_depth_b @ R_ab.T) / s_a)[:, :, None]
        W = m.sqrt_info
        jacobians[0] = whiten_rows(W, J_a)
        jacobians[1] = whiten_rows(W, J_b)
        jacobians[2] = whiten_rows(W, J_sa)
        jacobians[3] = whiten_rows(W, J_sb)
    return np.einsum("nij,nj->ni", m.sqrt_info, e).reshape(-1)


def make_match3d_factor(m: Match3DMeasurement, keys, noise=None) -> gtsam.CustomFactor:
    """Bind a view pair's matches into one factor (whitening is already in ``m.sqrt_info``)."""
    noise = noise or gtsam.noiseModel.Unit.Create(m.dim)
    return gtsam.CustomFactor(noise, list(keys), partial(match3d_error, m))
