"""2D reprojection of matched pixels, both ways across a view pair (Calib3R eq. 5).

Direction a -> b: the point back-projected from view a,
``P_a = s_a * d_a(p) * ray_a(p)``, is moved into camera b and projected with b's
intrinsics, and compared with the matched pixel:

    Q_b = b_T_a * P_a,     r_p = W_p (pi(K_b, Q_b) - u_b(p))        (2 rows per match)

and symmetrically b -> a. ``pi`` is the pinhole projection (OpenCV pixel
convention). The residual is invariant to a global change of scale. ``W_p`` is
a fixed (2, 2) square-root information in 1/pixel. Error dimension: 4N.

Note: the 3D match factor already carries the pixel and depth noise of the same
matches; adding this factor counts that information a second time (the
covariance becomes over-confident), so the solver leaves it off by default.

Keys: ``[base_T_a (Pose3), base_T_b (Pose3), s_a (double), s_b (double)]`` and, when
the measurement has a basis, the views' depth corrections ``[c_a, c_b (Vector K)]`` applied
as in factors.match3d: ``P = s (1 + phi . c) d ray``.
"""

from dataclasses import dataclass
from functools import partial

import gtsam
import numpy as np

from factors._lie import skew, whiten_rows
from factors.compression import make_compressed_factor


@dataclass(frozen=True)
class ReprojectionMeasurement:
    ray_depth_a: np.ndarray  # (N, 3) d_a * ray_a
    ray_depth_b: np.ndarray  # (N, 3) d_b * ray_b
    uv_a: np.ndarray  # (N, 2) matched pixels in view a
    uv_b: np.ndarray  # (N, 2) matched pixels in view b
    K_a: np.ndarray  # (3, 3)
    K_b: np.ndarray  # (3, 3)
    sqrt_info: np.ndarray  # (N, 2, 2), 1/pixel, used for both directions
    basis_a: np.ndarray | None = None  # (N, K) depth-correction basis at the matches in a
    basis_b: np.ndarray | None = None

    @property
    def dim(self) -> int:
        return 4 * len(self.uv_a)


def transform_one_way(points_src, src_T_dst: gtsam.Pose3, s_src):
    """``Q = dst_T_src * (s_src * points_src)`` (N, 3) and its Jacobians (N, 3, d) w.r.t. right
    perturbations of base_T_src and base_T_dst (d = 6 each) and s_src (d = 1)."""
    dst_T_src = src_T_dst.inverse()
    R = dst_T_src.rotation().matrix()
    P = s_src * points_src
    Q = P @ R.T + dst_T_src.translation()
    n = len(Q)
    # Q = R_dst^T (R_src P + t_src - t_dst); right perturbations of src and dst poses.
    dQ_src = np.concatenate([-R @ skew(P), np.broadcast_to(R, (n, 3, 3))], axis=2)
    dQ_dst = np.concatenate([skew(Q), -np.broadcast_to(np.eye(3), (n, 3, 3))], axis=2)
    dQ_s = (points_src @ R.T)[:, :, None]
    return Q, [dQ_src, dQ_dst, dQ_s]


def _project_one_way(ray_depth_src, uv_dst, K_dst, src_T_dst: gtsam.Pose3, s_src, basis=None, c=None):
    """Residual (N, 2) and Jacobians w.r.t. [xi_src (6), xi_dst (6), s_src (1)] (and c_src (K) with
    a basis) of one direction."""
    pd = ray_depth_src
    if basis is not None:
        ray_depth_src = pd * (1 + basis @ c)[:, None]
    Q, (dQ_src, dQ_dst, dQ_s) = transform_one_way(ray_depth_src, src_T_dst, s_src)
    R = src_T_dst.rotation().matrix().T
    x, y, z = Q[:, 0], Q[:, 1], Q[:, 2]
    fx, fy, cx, cy = K_dst[0, 0], K_dst[1, 1], K_dst[0, 2], K_dst[1, 2]
    uv = np.stack([fx * x / z + cx, fy * y / z + cy], axis=1)
    n = len(Q)
    d_pi = np.zeros((n, 2, 3))
    d_pi[:, 0, 0], d_pi[:, 0, 2] = fx / z, -fx * x / z**2
    d_pi[:, 1, 1], d_pi[:, 1, 2] = fy / z, -fy * y / z**2
    J = [d_pi @ dQ_src, d_pi @ dQ_dst, d_pi @ dQ_s]
    if basis is not None:  # d Q / d c = s R pd phi^T
        J.append(d_pi @ ((s_src * pd @ R.T)[:, :, None] * basis[:, None, :]))
    return uv - uv_dst, J


def reprojection_error(m: ReprojectionMeasurement, this: gtsam.CustomFactor, values: gtsam.Values,
                       jacobians) -> np.ndarray:
    keys = this.keys()
    base_T_a, base_T_b = values.atPose3(keys[0]), values.atPose3(keys[1])
    s_a, s_b = values.atDouble(keys[2]), values.atDouble(keys[3])
    c_a = values.atVector(keys[4]) if len(keys) == 6 else None
    c_b = values.atVector(keys[5]) if len(keys) == 6 else None
    a_T_b = base_T_a.between(base_T_b)
    r_ab, J_ab = _project_one_way(m.ray_depth_a, m.uv_b, m.K_b, a_T_b, s_a, m.basis_a, c_a)
    r_ba, J_ba = _project_one_way(m.ray_depth_b, m.uv_a, m.K_a, a_T_b.inverse(), s_b, m.basis_b, c_b)
    W = m.sqrt_info
    if jacobians is not None:
        def stack(J1, J2):
            return np.vstack([whiten_rows(W, J1), whiten_rows(W, J2)])

        zero_s = np.zeros_like(J_ab[2])
        jacobians[0] = stack(J_ab[0], J_ba[1])
        jacobians[1] = stack(J_ab[1], J_ba[0])
        jacobians[2] = stack(J_ab[2], zero_s)
        jacobians[3] = stack(zero_s, J_ba[2])
        if len(keys) == 6:
            jacobians[4] = stack(J_ab[3], np.zeros_like(J_ab[3]))
            jacobians[5] = stack(np.zeros_like(J_ba[3]), J_ba[3])
    return np.concatenate([np.einsum("nij,nj->ni", W, r_ab).reshape(-1),
                           np.einsum("nij,nj->ni", W, r_ba).reshape(-1)])


def make_reprojection_factor(m: ReprojectionMeasurement, keys, compress: bool = True) -> gtsam.CustomFactor:
    """One factor for both directions of a pair; ``compress``: D + 1 rows (factors.compression)."""
    if compress:
        k = [] if m.basis_a is None else [m.basis_a.shape[1], m.basis_b.shape[1]]
        return make_compressed_factor(reprojection_error, m, keys, [6, 6, 1, 1] + k)
    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(m.dim), list(keys), partial(reprojection_error, m))
