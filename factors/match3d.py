"""3D match between the back-projected matched pixels of a view pair (Calib3R eq. 4).

For each match p of the view pair (a, b) the two predicted depths are lifted to
3D points in their cameras,

    P_a = s_a * (1 + phi_a(p) . c_a) * d_a(p) * ray_a(p),     (likewise P_b)

with ``ray = K^-1 [u, v, 1]`` (z = 1), ``d`` the frontend's depth, ``s`` the view's
depth scale (metres per frontend unit) and ``c`` an optional low-dimensional
smooth depth correction on the basis ``phi`` (normalised image coordinates; the
frontend's depth errors are smooth, and a scale alone cannot absorb them). The
residual compares the two points in camera a's frame, normalised by ``s_a``:

    e_p = (P_a - a_T_b * P_b) / s_a,      a_T_b = base_T_a^-1 * base_T_b,
    r_p = W_p e_p                                              (3 rows per match)

Dividing by ``s_a`` makes the residual invariant to a global change of scale,
so the scene factors carry no pull towards a smaller reconstruction (a plain
metric residual rewards shrinking it and biases the metric scale). ``W_p`` is a
fixed (3, 3) square-root information in the unit of view a's frontend depth:
per-point covariance from pixel and depth noise, confidence and robust weight,
built by the caller. Error dimension: 3N, dimensionless after whitening.

Keys: ``[base_T_a, base_T_b (Pose3), s_a, s_b (double)]`` and, when the
measurement has a basis, ``[c_a, c_b (Vector K)]``.
"""

from dataclasses import dataclass
from functools import partial

import gtsam
import numpy as np

from factors.compression import make_compressed_factor


@dataclass(frozen=True)
class Match3DMeasurement:
    """Everything a 3D match factor needs about one view pair; N matches."""

    ray_depth_a: np.ndarray  # (N, 3) d_a * ray_a: point in cam a at unit depth scale
    ray_depth_b: np.ndarray  # (N, 3) d_b * ray_b
    sqrt_info: np.ndarray  # (N, 3, 3) W_p, applied to e_p
    basis_a: np.ndarray | None = None  # (N, K) depth-correction basis at the matches in a
    basis_b: np.ndarray | None = None  # (N, K)

    def __post_init__(self):
        n = len(self.ray_depth_a)
        assert self.ray_depth_a.shape == (n, 3) and self.ray_depth_b.shape == (n, 3)
        assert self.sqrt_info.shape == (n, 3, 3)
        assert (self.basis_a is None) == (self.basis_b is None)

    @property
    def dim(self) -> int:
        return 3 * len(self.ray_depth_a)


def _corrected(m: Match3DMeasurement, c_a, c_b):
    if m.basis_a is None:
        return m.ray_depth_a, m.ray_depth_b
    return m.ray_depth_a * (1 + m.basis_a @ c_a)[:, None], m.ray_depth_b * (1 + m.basis_b @ c_b)[:, None]


def match3d_residuals(m: Match3DMeasurement, base_T_a: gtsam.Pose3, base_T_b: gtsam.Pose3,
                      s_a: float, s_b: float, c_a=None, c_b=None) -> np.ndarray:
    """Unwhitened per-match residuals e_p (N, 3) in view a's frontend-depth unit."""
    g_a, g_b = _corrected(m, c_a, c_b)
    a_T_b = base_T_a.between(base_T_b)
    Q = (s_b * g_b) @ a_T_b.rotation().matrix().T + a_T_b.translation()
    return g_a - Q / s_a


def match3d_error(m: Match3DMeasurement, this: gtsam.CustomFactor, values: gtsam.Values,
                  jacobians) -> np.ndarray:
    keys = this.keys()
    e, WJ, blocks = match3d_whitened(m, keys, values, jacobians is not None)
    if jacobians is not None:
        for i, (a, b) in enumerate(blocks):
            jacobians[i] = WJ[:, a:b]
    return e


def match3d_whitened(m: Match3DMeasurement, keys, values: gtsam.Values, jacobian: bool = True):
    """(whitened residual (3N,), whitened Jacobian (3N, D) or None, each key's column range in it):
    :func:`match3d_error`'s numbers with the Jacobian as one array, for a caller that needs it whole
    (solver/graph.scene_linearisation)."""
    base_T_a, base_T_b = values.atPose3(keys[0]), values.atPose3(keys[1])
    s_a, s_b = values.atDouble(keys[2]), values.atDouble(keys[3])
    c_a = values.atVector(keys[4]) if len(keys) == 6 else None
    c_b = values.atVector(keys[5]) if len(keys) == 6 else None
    g_a, g_b = _corrected(m, c_a, c_b)
    a_T_b = base_T_a.between(base_T_b)
    R_ab = a_T_b.rotation().matrix()
    P_b = s_b * g_b
    Q = P_b @ R_ab.T + a_T_b.translation()
    e = g_a - Q / s_a
    W = m.sqrt_info
    WJ, blocks = None, None
    if jacobian:
        # The whitened blocks W_p dE_p/dx, written from (N, 3) products and cross products rather
        # than W applied to an assembled (N, 3, D) Jacobian (a batched product of 3x3 matrices, 4x
        # the time at 700 matches; the same numbers to rounding). With w_i the rows of W_p:
        # w_i^T skew(q) = (w_i x q)^T and R skew(p) = skew(R p) R.
        #   d e/d xi_a = [-skew(Q) | I] / s_a          -> rows (Q x w_i) / s_a, W / s_a
        #   d e/d xi_b = [R_ab skew(P_b) | -R_ab] / s_a -> rows (M_i x P_b) / s_a, -M / s_a, M = W R_ab
        #   d e/d s_a = Q / s_a^2,  d e/d s_b = -(R_ab g_b) / s_a
        #   d e/d c_a = g0_a phi_a^T,  d e/d c_b = -(s_b / s_a) (R_ab g0_b) phi_b^T  (g0: uncorrected)
        n, inv = len(Q), 1.0 / s_a
        k = m.basis_a.shape[1] if len(keys) == 6 else 0
        M = (W.reshape(3 * n, 3) @ (R_ab * inv)).reshape(n, 3, 3)  # W R_ab / s_a
        WJ = np.empty((n, 3, 14 + 2 * k))
        _cross_rows(Q * inv, W, WJ[:, :, 0:3])
        np.multiply(W, inv, out=WJ[:, :, 3:6])
        _cross_rows(-P_b, M, WJ[:, :, 6:9])
        np.negative(M, out=WJ[:, :, 9:12])
        WJ[:, :, 12] = _apply(W, Q * inv**2)
        WJ[:, :, 13] = _apply(M, -g_b)
        if k:
            np.multiply(_apply(W, m.ray_depth_a)[:, :, None], m.basis_a[:, None, :], out=WJ[:, :, 14:14 + k])
            np.multiply(_apply(M, -s_b * m.ray_depth_b)[:, :, None], m.basis_b[:, None, :], out=WJ[:, :, 14 + k:])
        WJ = WJ.reshape(3 * n, -1)
        blocks = [(0, 6), (6, 12), (12, 13), (13, 14), (14, 14 + k), (14 + k, 14 + 2 * k)][:len(keys)]
    return _apply(W, e).reshape(-1), WJ, blocks


def _apply(W, v):
    """W_p v_p for a batch: (N, 3, 3), (N, 3) -> (N, 3)."""
    return W[:, :, 0] * v[:, :1] + W[:, :, 1] * v[:, 1:2] + W[:, :, 2] * v[:, 2:3]


def _cross_rows(q, A, out):
    """q_p x a_pi for each row a_pi of A_p, into ``out``: (N, 3), (N, 3, 3) -> (N, 3, 3), row i = q x a_i."""
    q0, q1, q2 = q[:, None, 0], q[:, None, 1], q[:, None, 2]
    out[:, :, 0] = q1 * A[:, :, 2] - q2 * A[:, :, 1]
    out[:, :, 1] = q2 * A[:, :, 0] - q0 * A[:, :, 2]
    out[:, :, 2] = q0 * A[:, :, 1] - q1 * A[:, :, 0]


def _whitened_whole(m: Match3DMeasurement, keys, values: gtsam.Values):
    """(whitened residual, whitened Jacobian (3N, D)) for the row compression."""
    return match3d_whitened(m, keys, values)[:2]


def make_match3d_factor(m: Match3DMeasurement, keys, compress: bool = True) -> gtsam.CustomFactor:
    """Bind a view pair's matches into one factor (whitening is already in ``m.sqrt_info``).

    With ``compress`` the factor has D + 1 rows instead of 3N (factors.compression: exact).
    """
    with_basis = m.basis_a is not None
    assert len(keys) == (6 if with_basis else 4)
    if compress:
        k = m.basis_a.shape[1] if with_basis else 0
        dims = [6, 6, 1, 1] + ([k, k] if with_basis else [])
        return make_compressed_factor(match3d_error, m, keys, dims, whole_fn=_whitened_whole)
    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(m.dim), list(keys), partial(match3d_error, m))


def depth_correction_basis(uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """Quadratic basis (N, 5) on normalised image coordinates x, y in [-1, 1]:
    ``[x, y, x^2, xy, y^2]`` (the constant term is the depth scale itself)."""
    x = 2 * uv[:, 0] / (width - 1) - 1
    y = 2 * uv[:, 1] / (height - 1) - 1
    return np.stack([x, y, x * x, x * y, y * y], axis=1)


DEPTH_CORRECTION_DIM = 5
