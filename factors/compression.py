"""Exact row compression of a many-row factor (square root of its normal equations).

A view-pair factor has 3N rows (thousands) but only D = sum of its keys' dimensions
columns. Levenberg-Marquardt needs only the cost ||r||^2, J^T J and J^T r. With
``J^T J = V diag(l) V^T`` (eigendecomposition, D x D; rank-deficient is fine: a single
pair never sees the similarity gauge), ``R = diag(sqrt l) V^T`` and ``z = R^+T J^T r``:

    ||J d + r||^2 = ||R d + z||^2 + rho^2,      rho^2 = ||r||^2 - ||z||^2

so the factor can hand GTSAM ``e = [z; rho]`` (D + 1 rows) with Jacobian ``[R; 0]``:
the same cost, the same normal equations and hence the same LM steps and marginals,
with GTSAM's linear algebra on D + 1 rows instead of 3N. At linearisation points
``rho = |r_perp|`` has zero first derivative (r_perp is orthogonal to range(J)), so the
zero last row is exact, not an approximation. Without Jacobians the error is
``[||r||, 0, ..., 0]`` — the same cost.
"""

from functools import partial

import gtsam
import numpy as np


def compressed_error(error_fn, measurement, dims, this, values, jacobians, whole_fn=None) -> np.ndarray:
    """``whole_fn(measurement, keys, values) -> (r, J)``: the error and its Jacobian as one (rows, D)
    array, where the error function builds it whole (saves splitting it into blocks and stacking
    them again); otherwise ``error_fn``'s blocks are stacked."""
    d = sum(dims)
    if jacobians is None:
        r = error_fn(measurement, this, values, None)
        out = np.zeros(d + 1)
        out[0] = np.linalg.norm(r)
        return out
    if whole_fn is not None:
        r, J = whole_fn(measurement, this.keys(), values)
    else:
        blocks = [None] * len(dims)
        r = error_fn(measurement, this, values, blocks)
        J = np.hstack(blocks)
    lam, V = np.linalg.eigh(J.T @ J)
    keep = lam > lam[-1] * 1e-13  # numerically zero directions carry no information
    sqrt_l = np.sqrt(np.where(keep, lam, 0.0))
    R = np.zeros((d + 1, d))
    R[:d] = sqrt_l[:, None] * V.T
    e = np.zeros(d + 1)
    e[:d] = np.where(keep, (V.T @ (J.T @ r)) / np.where(keep, sqrt_l, 1.0), 0.0)
    e[d] = np.sqrt(max(r @ r - e[:d] @ e[:d], 0.0))
    start = 0
    for i, n in enumerate(dims):
        jacobians[i] = np.ascontiguousarray(R[:, start:start + n])
        start += n
    return e


def make_compressed_factor(error_fn, measurement, keys, dims, whole_fn=None) -> gtsam.CustomFactor:
    """A CustomFactor of D + 1 rows equivalent to ``error_fn`` (whitened, unit noise); ``whole_fn``:
    see :func:`compressed_error`."""
    noise = gtsam.noiseModel.Unit.Create(sum(dims) + 1)
    return gtsam.CustomFactor(noise, list(keys), partial(compressed_error, error_fn, measurement, list(dims),
                                                         whole_fn=whole_fn))
