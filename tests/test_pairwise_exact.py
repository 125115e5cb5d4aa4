"""The pairwise frontend's faster steps give the same numbers as the straightforward ones they
replaced (frontends/pairwise/): the epipolar-band candidates (blocked, row-major), the dense
mutual ratio test (one column max, not the survivors' columns gathered), the sparse mutual ratio
test (segment reductions, not lexsorts), the RANSAC's stacked hand-eye rotations, and
the aggregation's cache (a view whose depths come out the same keeps its prediction object). Every
comparison is exact (np.array_equal), not to a tolerance: the live result's equality with the batch
``solve`` rests on it."""

from types import SimpleNamespace

import numpy as np

from calib3r_graph.frontends import pairwise as pw
from calib3r_graph.frontends.pairwise import geometry, robot
from calib3r_graph.io.dataset import opencv_camera
from calib3r_graph.geometry import hand_eye_rotation
from factors._lie import skew


def _dense_candidates(la, lb, xb, f, max_px):
    """The band test as one (n_a, n_b) product and a 2-d nonzero (the former guided_matches)."""
    thr = (max_px / f * np.hypot(la[:, 0], la[:, 1])).astype(np.float32)
    alg = la.astype(np.float32) @ xb.T.astype(np.float32)
    alg *= alg
    i, j = np.nonzero(alg < (thr * thr)[:, None])
    e = np.einsum("nk,nk->n", xb[j], la[i])
    ok = np.abs(e) * f / np.hypot(lb[j, 0], lb[j, 1]) < max_px
    return i[ok], j[ok]


def _lexsort_mutual_ratio(i, j, sim, ratio):
    """The sparse mutual ratio test by two lexsorts (the former _sparse_mutual_ratio)."""
    o = np.lexsort((-sim, i))
    i, j, sim = i[o], j[o], sim[o]
    first = np.r_[True, i[1:] != i[:-1]]
    has_second = np.r_[i[1:] == i[:-1], False] & first
    s1 = sim[first]
    s2 = np.full(len(s1), -1.0)
    s2[has_second[first]] = sim[np.flatnonzero(has_second) + 1]
    bi, bj = i[first], j[first]
    r = np.sqrt(np.maximum(2 - 2 * s1, 0)) / np.maximum(np.sqrt(np.maximum(2 - 2 * s2, 0)), 1e-9)
    o = np.lexsort((-sim, j))
    col_first = np.r_[True, j[o][1:] != j[o][:-1]]
    best_a = np.full(j.max() + 1, -1)
    best_a[j[o][col_first]] = i[o][col_first]
    keep = (best_a[bj] == bi) & (r < ratio)
    return bi[keep], bj[keep], r[keep]


def _random_rotation(rng):
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    return q * np.sign(np.linalg.det(q))


def _equal(xs, ys):
    return all(x.dtype == y.dtype and np.array_equal(x, y) for x, y in zip(xs, ys))


def test_epipolar_band_candidates_are_those_of_the_dense_test():
    """Blocks of 128 rows, a last block of one row folded into the one before (257 rows), and a
    camera pair whose epipole is in the image: the same (i, j), in the same order."""
    rng = np.random.default_rng(0)
    K = np.array([[1000.0, 0, 640], [0, 1000, 480], [0, 0, 1]])
    found = 0
    for n_a, n_b, t in [(257, 900, [1.0, 0.1, 0.0]), (1000, 1300, [0.1, 0.0, 1.0]), (40, 35, [0.3, 1.0, 0.2])]:
        R = _random_rotation(rng)
        E = skew(np.array(t) / np.linalg.norm(t)) @ R
        ua, ub = rng.uniform(0, 1280, (n_a, 2)), rng.uniform(0, 960, (n_b, 2))
        xa, xb = geometry._homogeneous_rays(K, ua), geometry._homogeneous_rays(K, ub)
        la, lb = xa @ E.T, xb @ E
        for max_px in (2.0, 8.7):
            got = geometry._epipolar_candidates(la, lb, xb, 1000.0, max_px)
            want = _dense_candidates(la, lb, xb, 1000.0, max_px)
            assert _equal(got, want)
            found += len(want[0])
    assert found > 1000


def test_sparse_mutual_ratio_is_that_of_the_lexsorts_with_ties_and_any_order():
    """Row-major and shuffled candidate lists, similarities with many exact ties and without."""
    rng = np.random.default_rng(1)
    levels = np.array([0.1, 0.5, 0.7, 0.9, 0.95], np.float32)
    for k in range(200):
        n = int(rng.integers(1, 400))
        u = np.unique(np.c_[rng.integers(0, 30, n), rng.integers(0, 30, n)], axis=0)
        u = u[rng.permutation(len(u))] if k % 2 else u
        sim = rng.choice(levels, len(u)) if k % 3 else rng.random(len(u)).astype(np.float32)
        i, j = u[:, 0], u[:, 1]
        assert _equal(geometry._sparse_mutual_ratio(i, j, sim, 0.8), _lexsort_mutual_ratio(i, j, sim, 0.8))


def _gathered_mutual_ratio(S, ratio):
    """The dense mutual ratio test with the survivors' columns gathered (the former _mutual_ratio)."""
    rows = np.arange(S.shape[0])
    best = S.argmax(1)
    s1 = S[rows, best]
    T = S.copy()
    T[rows, best] = -np.inf
    s2 = T.max(1)
    r = np.sqrt(np.maximum(2 - 2 * s1, 0)) / np.maximum(np.sqrt(np.maximum(2 - 2 * s2, 0)), 1e-9)
    keep = np.flatnonzero(r < ratio)
    keep = keep[S[:, best[keep]].max(0) <= s1[keep]]
    return rows[keep], best[keep], r[keep]


def test_dense_mutual_ratio_is_that_of_the_gathered_columns_with_ties():
    """Unit descriptors (many matches survive the ratio test) and similarities with exact ties: the
    same matches, ratios and order, and S as it was."""
    rng = np.random.default_rng(3)
    kept = 0
    for k in range(60):
        n_a, n_b = int(rng.integers(2, 300)), int(rng.integers(2, 300))
        if k % 2:
            S = rng.choice(np.array([0.2, 0.6, 0.9, 0.97], np.float32), (n_a, n_b))
        else:
            A = rng.standard_normal((n_a, 16)).astype(np.float32)
            B = np.r_[A[rng.permutation(n_a)[:min(n_a, n_b)]], rng.standard_normal((max(0, n_b - n_a), 16))]
            B = (B + 0.1 * rng.standard_normal(B.shape)).astype(np.float32)
            A /= np.linalg.norm(A, axis=1, keepdims=True)
            B /= np.linalg.norm(B, axis=1, keepdims=True)
            S = A @ B.T
        before = S.copy()
        got = geometry._mutual_ratio(S, 0.8)
        assert np.array_equal(S, before)
        assert _equal(got, _gathered_mutual_ratio(before, 0.8))
        kept += len(got[0])
    assert kept > 1000


def test_stacked_hand_eye_rotations_are_the_one_by_one_ones():
    rng = np.random.default_rng(2)
    alphas, betas = rng.standard_normal((50, 3)), rng.standard_normal((50, 3))
    I, J = rng.integers(0, 50, 300), rng.integers(0, 50, 300)
    stacked = robot._hand_eye_rotations(alphas[np.c_[I, J]], betas[np.c_[I, J]])
    for k in range(len(I)):
        R, _ = hand_eye_rotation(alphas[[I[k], J[k]]], betas[[I[k], J[k]]])
        assert np.array_equal(stacked[k], R)


def test_a_view_whose_depths_do_not_change_keeps_its_prediction_object():
    """A pair added to view v whose triangulation angle is too small to give depth: v is
    re-aggregated (its pairs changed), its depths come out the same, and the cached aggregation
    returns the very same prediction and matches as before; the outputs equal an uncached run."""
    rng = np.random.default_rng(3)
    cam = opencv_camera("cam0", (200, 150), np.array([[100.0, 0, 100], [0, 100, 75], [0, 0, 1]]), np.zeros(5))
    ds = SimpleNamespace(cameras={"cam0": cam})  # aggregate reads the cameras only
    n = 300
    uv = rng.uniform(5, 140, (n, 2))
    z = rng.uniform(1.0, 3.0, n)
    feats = {v: pw.Features(uv, np.zeros((n, 128), np.float32), np.arange(n)) for v in ("cam0/a", "cam0/b", "cam0/c")}

    def pair(a, b, angle_deg):
        idx = np.arange(n)
        return pw.PairGeometry(a, b, idx, idx, z * 1.0, z * 1.0, np.full(n, np.radians(angle_deg)), np.ones(n) * 0.5,
                               np.eye(3), np.array([1.0, 0, 0]))

    geoms = {("cam0/a", "cam0/b"): pair("cam0/a", "cam0/b", 10), ("cam0/b", "cam0/c"): pair("cam0/b", "cam0/c", 10)}
    opt = pw.PairwiseOptions()
    cache = {}
    views, pairs, _ = pw.aggregate(ds, feats, geoms, opt, cache=cache)
    more = {**geoms, ("cam0/a", "cam0/c"): pair("cam0/a", "cam0/c", 0.1)}  # below min_pair_angle_deg
    views2, pairs2, _ = pw.aggregate(ds, feats, more, opt, cache=cache)
    fresh, fresh_pairs, _ = pw.aggregate(ds, feats, more, opt)
    assert all(views2[v] is views[v] for v in views)
    assert {id(p) for p in pairs} <= {id(p) for p in pairs2}
    for v in fresh:
        assert np.array_equal(views2[v].depth, fresh[v].depth) and np.array_equal(views2[v].conf, fresh[v].conf)
    assert [(p.view_a, p.view_b) for p in pairs2] == [(p.view_a, p.view_b) for p in fresh_pairs]
    for p, q in zip(pairs2, fresh_pairs):
        assert _equal((p.uv_a, p.uv_b, p.conf), (q.uv_a, q.uv_b, q.conf))


def test_a_view_keeps_its_aggregation_until_its_pairs_regrow():
    """With ``regrow=2`` (a live session) a view aggregated from two pairs keeps its prediction
    object when a third arrives: the new pair's matches are exactly its keypoints where that view
    already had depth. At four pairs it is aggregated again, to what an uncached run gives."""
    rng = np.random.default_rng(5)
    cam = opencv_camera("cam0", (200, 150), np.array([[100.0, 0, 100], [0, 100, 75], [0, 0, 1]]), np.zeros(5))
    ds = SimpleNamespace(cameras={"cam0": cam})
    gx, gy = np.meshgrid(np.arange(20) * 9.0 + 10.3, np.arange(15) * 9.0 + 8.7)  # 2x2 splats never touch
    uv = np.c_[gx.ravel(), gy.ravel()]
    n = len(uv)
    z = rng.uniform(1.0, 3.0, n)
    names = [f"cam0/{k}" for k in "abcde"]
    feats = {v: pw.Features(uv, np.zeros((n, 128), np.float32), np.arange(n)) for v in names}

    def pair(b, lo, hi):
        idx = np.arange(lo, hi)
        return ("cam0/a", b), pw.PairGeometry("cam0/a", b, idx, idx, z[idx], z[idx], np.full(len(idx), 0.2),
                                              np.full(len(idx), 0.5), np.eye(3), np.array([1.0, 0, 0]))

    opt = pw.PairwiseOptions()
    geoms = dict([pair("cam0/b", 0, 200), pair("cam0/c", 0, 200)])
    cache = {}
    views, _, _ = pw.aggregate(ds, feats, geoms, opt, cache=cache, regrow=2.0)
    third = {**geoms, **dict([pair("cam0/d", 100, 300)])}
    views3, pairs3, _ = pw.aggregate(ds, feats, third, opt, cache=cache, regrow=2.0)
    assert views3["cam0/a"] is views["cam0/a"]
    ad = next(p for p in pairs3 if {p.view_a, p.view_b} == {"cam0/a", "cam0/d"})
    uv_a = ad.uv_a if ad.view_a == "cam0/a" else ad.uv_b
    assert len(uv_a) == 100 and np.array_equal(np.sort(uv_a[:, 0] * 1e3 + uv_a[:, 1]),
                                               np.sort(uv[100:200, 0] * 1e3 + uv[100:200, 1]))
    fresh3, fresh_pairs3, _ = pw.aggregate(ds, feats, third, opt)  # without the cache: all 200 of the new pair
    assert sum(len(p.conf) for p in fresh_pairs3 if "cam0/d" in (p.view_a, p.view_b)) == 200
    fourth = {**third, **dict([pair("cam0/e", 50, 250)])}
    views4, pairs4, _ = pw.aggregate(ds, feats, fourth, opt, cache=cache, regrow=2.0)
    fresh4, fresh_pairs4, _ = pw.aggregate(ds, feats, fourth, opt)
    assert views4["cam0/a"] is not views["cam0/a"]
    for v in fresh4:
        assert np.array_equal(views4[v].depth, fresh4[v].depth) and np.array_equal(views4[v].conf, fresh4[v].conf)
    for p, q in zip(pairs4, fresh_pairs4):
        assert (p.view_a, p.view_b) == (q.view_a, q.view_b)
        assert _equal((p.uv_a, p.uv_b, p.conf), (q.uv_a, q.uv_b, q.conf))
