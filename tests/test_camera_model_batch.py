"""camera_model.pair_sensitivities (many pairs at once) gives what a plain pair-by-pair form of the
same maths gives (per_pair_reference, below, kept here as the reference only): seeded synthetic
pairs of two cameras linearised with solver.graph.scene_linearisation, with and without the depth
correction. That the terms themselves are right is tests/test_camera_model.py's check against a
re-solve with a moved principal point."""

from types import SimpleNamespace

import gtsam
import numpy as np
import pytest

from calib3r_graph.io.predictions import split_view_id
from calib3r_graph.solver.camera_model import camera_parameters, pair_sensitivities
from calib3r_graph.solver.graph import Keys, NoiseOptions, depth_correction, scene_linearisation
from calib3r_graph.solver.observations import PairObservations
from factors.match3d import DEPTH_CORRECTION_DIM, depth_correction_basis

CAMERAS = ("cam0", "cam1")
VIEWS = [f"{c}/{f:04d}" for c in CAMERAS for f in range(4)]


def per_pair_reference(lin, values, keys, Ks, noise, thetas, steps):
    """One view pair's part of the sensitivities, or None when no parameter moves it: (its keys,
    J^T dE (D, m), dE^T dE (m, m), dE^T e (m,)) with e its whitened residual, J its whitened
    Jacobian and dE the change of e per +1 sigma of each parameter (``steps[j][view]``: that sigma
    on the view's grid), from the pair's factor linearised at ``values``
    (solver.graph.scene_linearisation: keys, kept observations, W, J, e); many pairs at once:
    camera_model.pair_sensitivities, which this plain form checks. The residual ``e_p = g_a - (s_b / s_a) R_ab g_b - t_ab / s_a``
    (factors.match3d, with ``g = (1 + phi . c) P`` the corrected lifted point) is affine in the lifted points, so a change
    ``d`` of them changes it by ``(1 + phi_a . c_a) d_a - (s_b / s_a) (1 + phi_b . c_b) R_ab d_b``
    exactly; :func:`_lift_change` gives ``d``'s one non-zero coordinate per parameter."""
    k, o, W, J, e = lin
    js = [j for j, (c, _, _) in enumerate(thetas) if c in (split_view_id(o.view_a)[0], split_view_id(o.view_b)[0])]
    if not js:
        return None
    ca, cb = split_view_id(o.view_a)[0], split_view_id(o.view_b)[0]
    s_a, s_b = values.atDouble(keys.scale(o.view_a)), values.atDouble(keys.scale(o.view_b))
    R_ab = values.atPose3(keys.pose(o.view_a)).between(values.atPose3(keys.pose(o.view_b))).rotation().matrix()
    alpha, beta = np.ones(len(o)), np.full(len(o), s_b / s_a)
    if noise.depth_correction_sigma > 0:
        alpha = alpha + o.basis_a @ depth_correction(values, keys, o.view_a)
        beta = beta * (1 + o.basis_b @ depth_correction(values, keys, o.view_b))
    # b's changes, rotated into a's frame and whitened (one matrix product for all points)
    WR = (W.reshape(-1, 3) @ R_ab).reshape(W.shape) if cb in (t[0] for t in thetas) else None
    dE = np.zeros((len(o), 3, len(thetas)))
    for j in js:
        c, p, _ = thetas[j]
        axis = p % 2
        if ca == c:
            dE[:, :, j] += W[:, :, axis] * (alpha * _lift_change(o.pts_a, Ks[o.view_a], p, steps[j][o.view_a]))[:, None]
        if cb == c:
            dE[:, :, j] -= WR[:, :, axis] * (beta * _lift_change(o.pts_b, Ks[o.view_b], p, steps[j][o.view_b]))[:, None]
    dE = dE.reshape(len(e), len(thetas))
    return k, J.T @ dE, dE.T @ dE, dE.T @ e


def _lift_change(pts, K, p, h):
    """How points lifted as ``z K^-1 [u, v, 1]`` (so ``x = (u - cx) z / fx``) change when parameter
    ``p`` of the grid's K moves by ``h`` (first order): only x for fx and cx (-x h / fx, -z h / fx),
    only y for fy and cy likewise; returns that one coordinate's change (N,)."""
    axis = p % 2
    return -(pts[:, axis] if p < 2 else pts[:, 2]) * h / K[axis, axis]


def scene(seed, correction):
    """(keys, values, Ks, noise, cameras, lins) of random pairs among VIEWS: every camera pair,
    one pair with too few weighted matches (no factor), one of mostly zero weights and one whose
    W and J are slices of larger arrays."""
    rng = np.random.default_rng(seed)
    keys = Keys(VIEWS, CAMERAS)
    values = gtsam.Values()
    Ks = {}
    for v in VIEWS:
        values.insert(keys.pose(v), gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.3, 3)), rng.normal(0, 0.2, 3)))
        values.insert(keys.scale(v), float(rng.uniform(0.5, 2.0)))
        values.insert(keys.correction(v), rng.normal(0, 0.02, DEPTH_CORRECTION_DIM))
        f = rng.uniform(200, 300)
        Ks[v] = np.array([[f, 0, rng.uniform(150, 170)], [0, f * 1.01, rng.uniform(110, 130)], [0, 0, 1]])
    cameras = {"cam0": SimpleNamespace(K=np.diag([500.0, 505.0, 1.0]), params_sigma=(2.0, 2.0, 5.0, 5.0)),
               "cam1": SimpleNamespace(K=np.diag([400.0, 400.0, 1.0]), params_sigma=(1.0, 0.0, 3.0, 0.0))}
    noise = NoiseOptions(depth_correction_sigma=0.02 if correction else 0.0)

    def pair(va, vb, n, w=None):
        uv_a, uv_b = rng.uniform(0, [320, 240], (n, 2)), rng.uniform(0, [320, 240], (n, 2))
        pts_a = np.c_[rng.normal(0, 0.5, (n, 2)), rng.uniform(0.5, 3.0, n)]
        pts_b = np.c_[rng.normal(0, 0.5, (n, 2)), rng.uniform(0.5, 3.0, n)]
        o = PairObservations(va, vb, uv_a, uv_b, pts_a, pts_b, np.ones(n), depth_correction_basis(uv_a, 320, 240),
                             depth_correction_basis(uv_b, 320, 240))
        return scene_linearisation(o, rng.uniform(0.2, 2.0, n) if w is None else w, values, keys, Ks, noise)

    lins = [pair(va, vb, int(rng.integers(20, 80))) for va, vb in
            [("cam0/0000", "cam0/0001"), ("cam0/0002", "cam1/0002"), ("cam1/0000", "cam1/0003"),
             ("cam1/0001", "cam0/0003"), ("cam0/0001", "cam0/0003")]]
    lins.append(None)
    lins.append(pair("cam0/0000", "cam1/0001", 30, np.r_[1.0, 1.0, np.zeros(28)]))  # < 3 weighted: no factor
    lins.append(pair("cam1/0002", "cam0/0000", 40, np.r_[np.ones(10), np.zeros(30)]))  # only the weighted kept
    k, o, W, J, e = pair("cam0/0003", "cam1/0003", 50)
    bigW, bigJ = np.zeros((70, 3, 3)), np.zeros((200, J.shape[1] + 3))
    bigW[10:60], bigJ[20:170, 2:2 + J.shape[1]] = W, J
    lins.append((k, o, bigW[10:60], bigJ[20:170, 2:2 + J.shape[1]], e))  # views of larger arrays
    assert lins[6] is None and len(lins[7][1]) == 10
    return keys, values, Ks, noise, cameras, lins


@pytest.mark.parametrize("correction", [True, False])
@pytest.mark.parametrize("only", [None, "cam0", "cam1"])
def test_batched_equals_per_pair(correction, only):
    """The same None positions, keys and arrays (1e-10 relative) as per_pair_reference pair by pair,
    where both cameras or only one have a stated sigma (pairs of the other camera alone: None)."""
    keys, values, Ks, noise, cameras, lins = scene(7, correction)
    if only is not None:
        cameras = {c: SimpleNamespace(K=cam.K, params_sigma=cam.params_sigma if c == only else None)
                   for c, cam in cameras.items()}
    thetas, steps = camera_parameters(keys, cameras, Ks)
    assert len(thetas) == {None: 6, "cam0": 4, "cam1": 2}[only]
    expected = [None if lin is None else per_pair_reference(lin, values, keys, Ks, noise, thetas, steps) for lin in lins]
    got = pair_sensitivities(lins, values, keys, Ks, noise, thetas, steps)
    assert [t is None for t in got] == [t is None for t in expected]
    assert sum(t is not None for t in got) == {None: 7, "cam0": 6, "cam1": 5}[only]
    for a, b in zip(expected, got):
        if a is None:
            continue
        assert b[0] == a[0]
        for x, y in zip(a[1:], b[1:]):
            assert y.shape == x.shape and np.abs(x).max() > 0
            np.testing.assert_allclose(y, x, rtol=1e-10, atol=1e-10 * np.abs(x).max())


def test_no_parameters_and_no_pairs():
    keys, values, Ks, noise, cameras, lins = scene(3, True)
    assert pair_sensitivities(lins, values, keys, Ks, noise, [], []) == [None] * len(lins)
    thetas, steps = camera_parameters(keys, cameras, Ks)
    assert pair_sensitivities([None, None], values, keys, Ks, noise, thetas, steps) == [None, None]
    assert pair_sensitivities([], values, keys, Ks, noise, thetas, steps) == []
