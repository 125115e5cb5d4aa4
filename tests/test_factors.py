"""Every factor: analytic Jacobians against central differences at random points with a
non-zero residual, Jacobian shapes, and the same error with and without Jacobians."""

import gtsam
import numpy as np
import pytest

import factors
from factors.hand_eye import robot_pose_noise_covariance


def random_pose(rng, t_scale=0.5) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3) * t_scale)


def numeric_jacobians(error_fn, values, keys, eps=1e-6):
    """Central differences of error_fn(values) along each key's tangent space."""
    cols = []
    for k in keys:
        try:
            pose = values.atPose3(k)
            J = np.zeros((len(error_fn(values)), 6))
            for i in range(6):
                d = np.zeros(6)
                d[i] = eps
                vp, vm = gtsam.Values(values), gtsam.Values(values)
                vp.update(k, pose.retract(d))
                vm.update(k, pose.retract(-d))
                J[:, i] = (error_fn(vp) - error_fn(vm)) / (2 * eps)
        except RuntimeError:
            try:
                x = np.atleast_1d(values.atDouble(k))
                scalar = True
            except RuntimeError:
                x, scalar = values.atVector(k), False
            J = np.zeros((len(error_fn(values)), len(x)))
            for i in range(len(x)):
                d = np.zeros(len(x))
                d[i] = eps
                vp, vm = gtsam.Values(values), gtsam.Values(values)
                vp.update(k, float((x + d)[0]) if scalar else x + d)
                vm.update(k, float((x - d)[0]) if scalar else x - d)
                J[:, i] = (error_fn(vp) - error_fn(vm)) / (2 * eps)
        cols.append(J)
    return cols


def check_factor(error_fn_bound, factor, values, atol=1e-6, rtol=1e-5):
    keys = list(factor.keys())
    e0 = error_fn_bound(factor, values, None)
    assert np.linalg.norm(e0) > 1e-3, "test point must have a non-zero residual"
    jac = [None] * len(keys)
    e1 = error_fn_bound(factor, values, jac)
    np.testing.assert_array_equal(e0, e1)
    numeric = numeric_jacobians(lambda v: error_fn_bound(factor, v, None), values, keys)
    for i, (Ja, Jn) in enumerate(zip(jac, numeric)):
        assert Ja.shape == Jn.shape, f"Jacobian {i}: shape {Ja.shape} != {Jn.shape}"
        np.testing.assert_allclose(Ja, Jn, atol=atol, rtol=rtol, err_msg=f"Jacobian {i}")
    # GTSAM's own linearisation agrees with the error (and does not crash on shapes).
    gf = factor.linearize(values)
    assert gf.rows() == len(e0)


def pair_values(rng):
    v = gtsam.Values()
    v.insert(0, random_pose(rng))
    v.insert(1, random_pose(rng))
    v.insert(2, float(rng.uniform(0.5, 2.0)))
    v.insert(3, float(rng.uniform(0.5, 2.0)))
    return v


def near_pair_values(rng) -> gtsam.Values:
    """Two camera poses near identity (keys 0, 1), so points in front of one are in front of the other."""
    v = gtsam.Values()
    v.insert(0, gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.05), rng.normal(size=3) * 0.05))
    v.insert(1, gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.05), rng.normal(size=3) * 0.05))
    return v


def random_points(rng, n):
    uv = rng.uniform([0, 0], [640, 480], size=(n, 2))
    K = np.array([[500.0, 0, 320], [0, 510, 240], [0, 0, 1]])
    rays = np.c_[uv, np.ones(n)] @ np.linalg.inv(K).T
    depth = rng.uniform(0.5, 2.0, size=n)
    return uv, K, rays * depth[:, None]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_match3d_jacobians(seed):
    rng = np.random.default_rng(seed)
    n = 7
    _, _, pa = random_points(rng, n)
    _, _, pb = random_points(rng, n)
    A = rng.normal(size=(n, 3, 3))
    m = factors.Match3DMeasurement(pa, pb, A)
    f = factors.make_match3d_factor(m, [0, 1, 2, 3], compress=False)
    check_factor(lambda fac, v, H: factors.match3d_error(m, fac, v, H), f, pair_values(rng))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_reprojection_jacobians(seed):
    rng = np.random.default_rng(seed)
    n = 5
    uv_a, K_a, pa = random_points(rng, n)
    uv_b, K_b, pb = random_points(rng, n)
    v = near_pair_values(rng)  # both cameras see the points, with error
    v.insert(2, float(rng.uniform(0.8, 1.2)))
    v.insert(3, float(rng.uniform(0.8, 1.2)))
    W = np.eye(2)[None] * rng.uniform(0.5, 2, size=(n, 1, 1))
    m = factors.ReprojectionMeasurement(pa, pb, uv_a, uv_b, K_a, K_b, W)
    f = factors.make_reprojection_factor(m, [0, 1, 2, 3], compress=False)
    check_factor(lambda fac, vals, H: factors.reprojection_error(m, fac, vals, H), f, v, atol=1e-4)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_robot_pose_jacobians(seed):
    rng = np.random.default_rng(seed)
    E = random_pose(rng)
    v = gtsam.Values()
    v.insert(10, random_pose(rng, 0.1))
    v.insert(11, random_pose(rng))
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 1.0)
    f = factors.make_robot_pose_factor(E, [10, 11], noise)
    check_factor(lambda fac, vals, H: factors.robot_pose_error(E, fac, vals, H), f, v)


def test_robot_pose_error_zero_at_consistent_poses():
    rng = np.random.default_rng(5)
    E, X = random_pose(rng), random_pose(rng, 0.1)
    v = gtsam.Values()
    v.insert(0, X)
    v.insert(1, E.compose(X))
    e = factors.robot_pose_error(E, factors.make_robot_pose_factor(E, [0, 1], gtsam.noiseModel.Unit.Create(6)), v, None)
    np.testing.assert_allclose(e, 0, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_relative_hand_eye_jacobians(seed):
    rng = np.random.default_rng(seed)
    A = random_pose(rng)
    v = gtsam.Values()
    v.insert(0, random_pose(rng, 0.1))
    v.insert(1, random_pose(rng))
    v.insert(2, random_pose(rng))
    v.insert(3, float(rng.uniform(0.5, 2)))
    f = factors.make_relative_hand_eye_factor(A, [0, 1, 2, 3], gtsam.noiseModel.Unit.Create(6))
    check_factor(lambda fac, vals, H: factors.relative_hand_eye_error(A, fac, vals, H), f, v)


def test_relative_hand_eye_zero_when_ax_equals_xb():
    rng = np.random.default_rng(3)
    X, E1, E2 = random_pose(rng, 0.1), random_pose(rng), random_pose(rng)
    lam = 0.37
    v = gtsam.Values()
    v.insert(0, X)
    # visual poses in reconstruction units: metric translation / lambda
    for k, E in ((1, E1), (2, E2)):
        C = E.compose(X)
        v.insert(k, gtsam.Pose3(C.rotation(), C.translation() / lam))
    v.insert(3, lam)
    f = factors.make_relative_hand_eye_factor(E1.between(E2), [0, 1, 2, 3], gtsam.noiseModel.Unit.Create(6))
    np.testing.assert_allclose(factors.relative_hand_eye_error(E1.between(E2), f, v, None), 0, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rigidity_jacobians(seed):
    rng = np.random.default_rng(seed)
    v = gtsam.Values()
    for k in range(4):
        v.insert(k, random_pose(rng))
    f = factors.make_rigidity_factor([0, 1, 2, 3], gtsam.noiseModel.Unit.Create(6))
    check_factor(lambda fac, vals, H: factors.rigidity_error(None, fac, vals, H), f, v)


def test_scale_gauge_jacobians():
    rng = np.random.default_rng(0)
    v = gtsam.Values()
    for k in range(5):
        v.insert(k, float(rng.uniform(0.5, 2)))
    f = factors.make_scale_gauge_factor(list(range(5)), gtsam.noiseModel.Unit.Create(1))
    check_factor(lambda fac, vals, H: factors.scale_gauge_error(None, fac, vals, H), f, v)


def test_robot_noise_covariance_matches_monte_carlo():
    """The propagated 6x6 covariance predicts the spread of the error under flange noise."""
    rng = np.random.default_rng(0)
    X = random_pose(rng, 0.1)
    E = random_pose(rng)
    sr, st = np.deg2rad(0.05), 0.001
    cov = robot_pose_noise_covariance(X, sr, st)
    v = gtsam.Values()
    v.insert(0, X)
    v.insert(1, E.compose(X))
    errs = []
    for _ in range(4000):
        E_noisy = E.compose(gtsam.Pose3.Expmap(np.r_[rng.normal(size=3) * sr, rng.normal(size=3) * st]))
        f = factors.make_robot_pose_factor(E_noisy, [0, 1], gtsam.noiseModel.Unit.Create(6))
        errs.append(factors.robot_pose_error(E_noisy, f, v, None))
    emp = np.cov(np.array(errs).T)
    np.testing.assert_allclose(np.sqrt(np.diag(emp)), np.sqrt(np.diag(cov)), rtol=0.08)


@pytest.mark.parametrize("seed", [0, 1])
def test_match3d_with_depth_correction_jacobians(seed):
    from factors.match3d import depth_correction_basis

    rng = np.random.default_rng(seed)
    n = 6
    uv_a, _, pa = random_points(rng, n)
    uv_b, _, pb = random_points(rng, n)
    m = factors.Match3DMeasurement(pa, pb, rng.normal(size=(n, 3, 3)),
                                   depth_correction_basis(uv_a, 640, 480), depth_correction_basis(uv_b, 640, 480))
    v = pair_values(rng)
    v.insert(4, rng.normal(size=5) * 0.05)
    v.insert(5, rng.normal(size=5) * 0.05)
    f = factors.make_match3d_factor(m, [0, 1, 2, 3, 4, 5], compress=False)
    check_factor(lambda fac, vals, H: factors.match3d_error(m, fac, vals, H), f, v)


def _normal_equations(factor, values):
    A, b = factor.linearize(values).jacobian()
    return A.T @ A, A.T @ b, float(b @ b)


@pytest.mark.parametrize("with_basis,n", [(False, 40), (True, 40), (True, 3)])
def test_compressed_factor_is_exactly_equivalent(with_basis, n):
    """Same cost, same J^T J and J^T r as the uncompressed factor (also with fewer rows than columns)."""
    from factors.match3d import depth_correction_basis

    rng = np.random.default_rng(7)
    uv_a, _, pa = random_points(rng, n)
    uv_b, _, pb = random_points(rng, n)
    basis = (depth_correction_basis(uv_a, 640, 480), depth_correction_basis(uv_b, 640, 480)) if with_basis else (None, None)
    m = factors.Match3DMeasurement(pa, pb, rng.normal(size=(n, 3, 3)), *basis)
    keys = [0, 1, 2, 3] + ([4, 5] if with_basis else [])
    v = pair_values(rng)
    if with_basis:
        v.insert(4, rng.normal(size=5) * 0.05)
        v.insert(5, rng.normal(size=5) * 0.05)
    full = factors.make_match3d_factor(m, keys, compress=False)
    comp = factors.make_match3d_factor(m, keys, compress=True)
    assert comp.dim() == (25 if with_basis else 15)
    assert comp.error(v) == pytest.approx(full.error(v), rel=1e-10)
    H1, g1, c1 = _normal_equations(full, v)
    H2, g2, c2 = _normal_equations(comp, v)
    np.testing.assert_allclose(H2, H1, rtol=1e-9, atol=1e-9 * np.abs(H1).max())
    np.testing.assert_allclose(g2, g1, rtol=1e-9, atol=1e-9 * np.abs(g1).max())
    assert c2 == pytest.approx(c1, rel=1e-9)


def test_compressed_reprojection_factor_is_equivalent():
    rng = np.random.default_rng(8)
    n = 30
    uv_a, K_a, pa = random_points(rng, n)
    uv_b, K_b, pb = random_points(rng, n)
    v = near_pair_values(rng)
    v.insert(2, 1.1)
    v.insert(3, 0.9)
    m = factors.ReprojectionMeasurement(pa, pb, uv_a, uv_b, K_a, K_b, np.eye(2)[None].repeat(n, 0))
    full = factors.make_reprojection_factor(m, [0, 1, 2, 3], compress=False)
    comp = factors.make_reprojection_factor(m, [0, 1, 2, 3])
    assert comp.error(v) == pytest.approx(full.error(v), rel=1e-10)
    H1, g1, _ = _normal_equations(full, v)
    H2, g2, _ = _normal_equations(comp, v)
    np.testing.assert_allclose(H2, H1, rtol=1e-8, atol=1e-8 * np.abs(H1).max())
    np.testing.assert_allclose(g2, g1, rtol=1e-8, atol=1e-8 * np.abs(g1).max())


@pytest.mark.parametrize("seed", [0, 1])
def test_pattern_factor_jacobians(seed):
    from factors.pattern import PatternMeasurement, make_pattern_factor, pattern_error

    rng = np.random.default_rng(seed)
    corners = np.c_[np.mgrid[0:4, 0:3].reshape(2, -1).T * 0.03, np.zeros(12)]
    v = gtsam.Values()
    v.insert(0, gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.05), np.array([0, 0, 0.5]) + rng.normal(size=3) * 0.02))
    v.insert(1, gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.05), rng.normal(size=3) * 0.02))
    intrinsics = np.array([500.0, 500, 320, 240, -0.2, 0.1, 1e-3, -2e-3])  # with distortion
    m = PatternMeasurement(corners, rng.uniform(200, 400, size=(12, 2)), intrinsics)
    f = make_pattern_factor(m, [0, 1])
    check_factor(lambda fac, vals, H: pattern_error(m, fac, vals, H), f, v, atol=1e-4)


def test_pattern_factor_with_intrinsics_jacobians():
    from factors.pattern import PatternMeasurement, make_pattern_factor, pattern_error

    rng = np.random.default_rng(3)
    corners = np.c_[np.mgrid[0:4, 0:3].reshape(2, -1).T * 0.03, np.zeros(12)]
    v = gtsam.Values()
    v.insert(0, gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.05), np.array([0, 0, 0.5])))
    v.insert(1, gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.05), rng.normal(size=3) * 0.02))
    v.insert(2, np.array([510.0, 495.0, 318.0, 244.0, -0.25, 0.15, 2e-3, -1e-3]))
    m = PatternMeasurement(corners, rng.uniform(200, 400, size=(12, 2)), np.zeros(8))
    f = make_pattern_factor(m, [0, 1, 2])
    check_factor(lambda fac, vals, H: pattern_error(m, fac, vals, H), f, v, atol=1e-4)


@pytest.mark.parametrize("with_intrinsics", [False, True])
def test_pattern_factor_with_board_scale_jacobians(with_intrinsics):
    from factors.pattern import PatternMeasurement, make_pattern_factor, pattern_error

    rng = np.random.default_rng(5)
    corners = np.c_[np.mgrid[0:4, 0:3].reshape(2, -1).T * 0.03, np.zeros(12)]
    v = gtsam.Values()
    v.insert(0, gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.05), np.array([0, 0, 0.5])))
    v.insert(1, gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.05), rng.normal(size=3) * 0.02))
    keys = [0, 1]
    if with_intrinsics:
        v.insert(2, np.array([510.0, 495.0, 318.0, 244.0, 0.1, -0.05, -1e-3, 3e-3]))
        keys.append(2)
    v.insert(3, 1.013)
    m = PatternMeasurement(corners, rng.uniform(200, 400, size=(12, 2)), np.array([500.0, 500, 0, 0, -0.2, 0.1, 0, 0]),
                           0.5, True)
    f = make_pattern_factor(m, keys + [3])
    check_factor(lambda fac, vals, H: pattern_error(m, fac, vals, H), f, v, atol=1e-4)


def test_reprojection_with_depth_correction_jacobians():
    from factors.match3d import depth_correction_basis

    rng = np.random.default_rng(4)
    n = 5
    uv_a, K_a, pa = random_points(rng, n)
    uv_b, K_b, pb = random_points(rng, n)
    v = near_pair_values(rng)
    v.insert(2, 1.05)
    v.insert(3, 0.95)
    v.insert(4, rng.normal(size=5) * 0.03)
    v.insert(5, rng.normal(size=5) * 0.03)
    m = factors.ReprojectionMeasurement(pa, pb, uv_a, uv_b, K_a, K_b, np.eye(2)[None].repeat(n, 0),
                                        depth_correction_basis(uv_a, 640, 480), depth_correction_basis(uv_b, 640, 480))
    f = factors.make_reprojection_factor(m, [0, 1, 2, 3, 4, 5], compress=False)
    check_factor(lambda fac, vals, H: factors.reprojection_error(m, fac, vals, H), f, v, atol=1e-4)
    comp = factors.make_reprojection_factor(m, [0, 1, 2, 3, 4, 5])
    assert comp.error(v) == pytest.approx(f.error(v), rel=1e-10)
