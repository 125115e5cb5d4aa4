"""camera_model.pair_sensitivities (many pairs at once) gives what pair_sensitivity gives pair by
pair: seeded synthetic pairs of two cameras linearised with solver.graph.scene_linearisation,
with and without the depth correction."""

from types import SimpleNamespace

import gtsam
import numpy as np
import pytest

from calib3r_graph.solver.camera_model import camera_parameters, pair_sensitivities, pair_sensitivity
from calib3r_graph.solver.graph import Keys, NoiseOptions, scene_linearisation
from calib3r_graph.solver.observations import PairObservations
from factors.match3d import DEPTH_CORRECTION_DIM, depth_correction_basis

CAMERAS = ("cam0", "cam1")
VIEWS = [f"{c}/{f:04d}" for c in CAMERAS for f in range(4)]


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
    """The same None positions, keys and arrays (1e-10 relative) as pair_sensitivity pair by pair,
    where both cameras or only one have a stated sigma (pairs of the other camera alone: None)."""
    keys, values, Ks, noise, cameras, lins = scene(7, correction)
    if only is not None:
        cameras = {c: SimpleNamespace(K=cam.K, params_sigma=cam.params_sigma if c == only else None)
                   for c, cam in cameras.items()}
    thetas, steps = camera_parameters(keys, cameras, Ks)
    assert len(thetas) == {None: 6, "cam0": 4, "cam1": 2}[only]
    expected = [None if lin is None else pair_sensitivity(lin, values, keys, Ks, noise, thetas, steps) for lin in lins]
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
