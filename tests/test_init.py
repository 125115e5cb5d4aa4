import gtsam
import numpy as np
import pytest

from calib3r_graph.errors import InputError
from calib3r_graph.geometry import ransac_sim3, umeyama
from calib3r_graph.solver.init import hand_eye_closed_form


def test_ransac_sim3_recovers_similarity_despite_outliers():
    rng = np.random.default_rng(0)
    src = rng.uniform(-1, 1, (500, 3)) + [0, 0, 3]
    R = gtsam.Rot3.Expmap([0.2, -0.1, 0.3]).matrix()
    s, t = 2.5, np.array([0.1, -0.4, 0.2])
    dst = s * src @ R.T + t + rng.normal(scale=0.002, size=src.shape)
    out = rng.choice(500, 100, replace=False)
    dst[out] = rng.uniform(-3, 3, (100, 3))
    s_hat, R_hat, t_hat, inl = ransac_sim3(src, dst, rng=rng)
    assert s_hat == pytest.approx(s, rel=1e-3)
    np.testing.assert_allclose(R_hat, R, atol=2e-3)
    np.testing.assert_allclose(t_hat, t, atol=1e-2)
    assert inl[out].mean() < 0.05 and inl[np.setdiff1d(np.arange(500), out)].mean() > 0.95


def _synthetic_chain(rng, n=8, lam_world=0.25):
    X = gtsam.Pose3(gtsam.Rot3.Expmap([0.1, 0.2, 1.5]), np.array([0.03, -0.02, 0.08]))
    E = {f"{i}": gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.6), rng.normal(size=3) * 0.3) for i in range(n)}
    world_T_base = gtsam.Pose3(gtsam.Rot3.Expmap([0.3, 0.1, -0.2]), np.array([1.0, 2.0, 0.5]))
    comp = {}
    for f, Ef in E.items():
        C = world_T_base.compose(Ef).compose(X)  # metric, arbitrary world
        comp[f"cam0/{f}"] = (gtsam.Pose3(C.rotation(), C.translation() / lam_world), 1.0)
    return X, E, comp


def test_closed_form_hand_eye_recovers_mount_and_scale():
    rng = np.random.default_rng(1)
    X, E, comp = _synthetic_chain(rng)
    ee_T_cam, scales = hand_eye_closed_form([comp], E)
    np.testing.assert_allclose(ee_T_cam["cam0"].matrix(), X.matrix(), atol=1e-9)
    assert scales[0] == pytest.approx(0.25, rel=1e-9)


def test_inverted_robot_poses_are_detected():
    rng = np.random.default_rng(2)
    _, E, comp = _synthetic_chain(rng)
    inverted = {f: p.inverse() for f, p in E.items()}
    with pytest.raises(InputError, match="inverted"):
        hand_eye_closed_form([comp], inverted, "robot_poses.csv")


def test_umeyama_exact():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(10, 3))
    R = gtsam.Rot3.Expmap([0.5, 0.1, -0.7]).matrix()
    s, R_hat, t = umeyama(src, 0.7 * src @ R.T + 1.0)
    assert s == pytest.approx(0.7)
    np.testing.assert_allclose(R_hat, R, atol=1e-12)


def test_inverse_cholesky_3x3_whitens():
    from calib3r_graph.solver.graph import inverse_cholesky_3x3

    rng = np.random.default_rng(4)
    A = rng.normal(size=(50, 3, 3))
    C = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(3)
    W = inverse_cholesky_3x3(C)
    np.testing.assert_allclose(np.swapaxes(W, 1, 2) @ W, np.linalg.inv(C), rtol=1e-9, atol=1e-9)
    assert np.allclose(np.triu(W, 1), 0)
