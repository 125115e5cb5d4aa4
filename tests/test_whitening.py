"""The scene factors' whitening (solver/graph.py): each match's square-root information is that of
the documented point covariance, at seeded random points, checked one point at a time."""

import gtsam
import numpy as np

from calib3r_graph.solver.graph import NoiseOptions, point_covariances, point_sqrt_info
from calib3r_graph.solver.observations import PairObservations


def _pair(rng, n=50):
    pts_a = rng.normal(size=(n, 3)) * [0.3, 0.2, 0.1] + [0, 0, 1.5]
    pts_b = rng.normal(size=(n, 3)) * [0.3, 0.2, 0.1] + [0, 0, 2.0]
    z = np.zeros((n, 0))
    return PairObservations("cam0/0", "cam0/1", np.zeros((n, 2)), np.zeros((n, 2)), pts_a, pts_b, np.ones(n), z, z)


def test_sqrt_info_whitens_the_documented_point_covariance():
    rng = np.random.default_rng(3)
    o = _pair(rng)
    K_a = np.array([[600.0, 0, 320], [0, 580.0, 240], [0, 0, 1]])
    K_b = np.array([[450.0, 0, 300], [0, 470.0, 200], [0, 0, 1]])
    noise = NoiseOptions(pixel_sigma_px=1.7, depth_sigma_rel=0.02)
    a_T_b = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3))
    ratio, weights = 1.3, rng.uniform(0.2, 2.0, len(o))
    W = point_sqrt_info(o, K_a, K_b, a_T_b, ratio, noise, weights)
    R = a_T_b.rotation().matrix()
    for i in range(len(o)):
        def cov(P, K):  # sigma_d^2 P P^T + diag((sigma_px z / fx)^2, (sigma_px z / fy)^2, 0)
            lat = (noise.pixel_sigma_px * P[2]) ** 2 * np.array([1 / K[0, 0] ** 2, 1 / K[1, 1] ** 2, 0.0])
            return noise.depth_sigma_rel ** 2 * np.outer(P, P) + np.diag(lat)
        C = cov(o.pts_a[i], K_a) + ratio ** 2 * R @ cov(o.pts_b[i], K_b) @ R.T
        info = weights[i] * np.linalg.inv(C)
        assert np.allclose(W[i].T @ W[i], info, rtol=1e-9, atol=1e-9 * np.abs(info).max())
        assert np.allclose(W[i], np.tril(W[i]))  # the inverse Cholesky factor: lower triangular
    C_a, C_b = point_covariances(o, K_a, K_b, noise)
    assert np.allclose(point_sqrt_info(o, K_a, K_b, a_T_b, ratio, noise, weights, (C_a, C_b)), W, rtol=0, atol=0)
