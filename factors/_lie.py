"""Small batched Lie-group helpers shared by the factors."""

import gtsam
import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """Batched cross-product matrices: (..., 3) -> (..., 3, 3), ``skew(a) @ b = a x b``."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def log_with_jacobian(pose: gtsam.Pose3) -> tuple[np.ndarray, np.ndarray]:
    """``Log(pose)`` (6,) and its derivative w.r.t. a right perturbation of ``pose`` (6, 6)."""
    H = np.zeros((6, 6), order="F")
    xi = gtsam.Pose3.Logmap(pose, H)
    return np.asarray(xi, dtype=np.float64), np.array(H)


def whiten_rows(sqrt_info: np.ndarray, J: np.ndarray) -> np.ndarray:
    """Apply per-match (N, k, k) square-root information to per-match Jacobians (N, k, d) -> (N*k, d)."""
    return np.einsum("nij,njd->nid", sqrt_info, J).reshape(-1, J.shape[-1])
