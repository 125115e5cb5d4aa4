"""Bilinear sampling of depth and confidence maps (solver/observations.py), at seeded random pixels."""

import numpy as np

from calib3r_graph.solver.observations import bilinear_taps, sample_bilinear, sample_taps


def _plane(h, w):
    y, x = np.mgrid[0:h, 0:w]
    return (1.0 + 2.0 * x + 3.0 * y).astype(np.float32)


def test_bilinear_is_exact_on_a_plane_and_flags_holes_and_outside():
    rng = np.random.default_rng(3)
    h, w = 40, 60
    img = _plane(h, w)
    img[10, 20] = 0.0  # a hole: every sample with it as a neighbour is not ok
    uv = np.c_[rng.uniform(-2, w + 1, 500), rng.uniform(-2, h + 1, 500)]
    val, ok = sample_bilinear(img, uv)
    inside = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] <= h - 1)
    near_hole = (np.abs(uv[:, 0] - 20) < 1) & (np.abs(uv[:, 1] - 10) < 1)
    assert np.array_equal(ok, inside & ~near_hole)
    expect = 1.0 + 2.0 * uv[:, 0] + 3.0 * uv[:, 1]
    assert np.max(np.abs(val[ok] - expect[ok])) < 1e-4  # float32 image: exact up to its rounding
    assert 0 < near_hole.sum() and (~inside).sum() > 20  # both cases were drawn


def test_one_set_of_taps_samples_two_maps_as_two_calls_do():
    rng = np.random.default_rng(4)
    h, w = 30, 50
    depth = rng.uniform(0.5, 2.0, (h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.2] = 0.0
    conf = rng.uniform(0.0, 1.0, (h, w)).astype(np.float32)
    uv = np.c_[rng.uniform(0, w - 1, 300), rng.uniform(0, h - 1, 300)]
    taps = bilinear_taps(depth.shape, uv)
    for img in (depth, conf):
        v1, ok1 = sample_taps(img, taps)
        v2, ok2 = sample_bilinear(img, uv)
        assert np.array_equal(v1, v2) and np.array_equal(ok1, ok2)
    # (and the value is the bilinear blend of the four neighbours)
    x0, y0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    fx, fy = uv[:, 0] - x0, uv[:, 1] - y0
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    blend = ((depth[y0, x0] * (1 - fx) + depth[y0, x1] * fx) * (1 - fy)
             + (depth[y1, x0] * (1 - fx) + depth[y1, x1] * fx) * fy)
    v, ok = sample_taps(depth, taps)
    assert 0.3 < ok.mean() < 0.7
    assert np.max(np.abs(v - blend)) < 1e-6
