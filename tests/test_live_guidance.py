"""Live guidance (solver/guidance.py): on an orbit, where the metric scale cannot be observed, the guide
proposes a move toward or away from the scene first, and the pose it proposes, rendered and added,
measures the scale. Fixed replay orders (live/run.py's replay with a list)."""

import gtsam
import numpy as np
import pytest

from calib3r_graph.io.dataset import load_dataset
from calib3r_graph.live import LiveSession
from calib3r_graph.live.run import replay
from calib3r_graph.simulate import render_poses

# An orbit like rwhe_kuka_2's (simulate.orbit_trajectory), small images: the pairwise RGB frontend on
# them. The targets are tight so that the session keeps proposing poses.
ORBIT = dict(seed=0, frames=6, trajectory="orbit", width=320, height=240, matches_per_pair=200,
             prediction_downsample=4, images=True)


def _scale_rel(up) -> float:
    lam, sigma = up.metric_scale["cam0"]
    return sigma / abs(lam)


def test_orbit_guidance_moves_toward_or_away_first_and_measures_the_scale(simulated, tmp_path):
    from calib3r_graph.solver.guidance import distance_band, scene_geometry

    root = simulated(**ORBIT)
    session = LiveSession(root, target_mm=0.5, target_deg=0.05, out=tmp_path / "live")
    frames = list(session.poses_known)
    for i, f in enumerate(frames):
        session.guide = i == len(frames) - 1  # proposals for the last orbit frame only (the test's time)
        up = session.add_frame(f, images={"cam0": str(root / "images" / "cam0" / f"{f}.png")})
    assert up.metric_scale and up.next_poses, up.message
    # the orbit: every camera at one distance (within 3 %), so the scale is weak
    _, dist = scene_geometry(session.sol)
    assert dist.max() / dist.min() < 1.1
    before = _scale_rel(up)
    assert before > 0.01, f"the orbit alone measures the scale to {before:.2%}: not the weak case this tests"
    assert up.next_kinds[0] in ("toward", "away"), up.next_kinds
    lo, hi = distance_band(dist)
    centroid, _ = scene_geometry(session.sol)
    X = session.sol.ee_T_cam["cam0"]
    E = gtsam.Pose3(np.array(up.next_poses[0]))
    d_new = np.linalg.norm(E.compose(X).translation() - centroid)
    assert lo - 1e-6 <= d_new <= hi + 1e-6 and abs(d_new / np.median(dist) - 1) >= 0.09
    up = session.add_frame("guided1", E, images=render_poses(root, {"g": E})["g"])
    assert "cam0/guided1" in session.sol.base_T_cam, up.message
    after = _scale_rel(up)
    assert after < before / 3, f"scale sigma {before:.2%} -> {after:.2%}"


@pytest.mark.parametrize("cut", [4])
def test_replay_takes_a_fixed_order(simulated, cut):
    root = simulated(seed=5, frames=6, cameras=1, matches_per_pair=300)
    frames = load_dataset(root).frames
    order = frames[::-1][:cut]
    session = LiveSession(root, predictions="sim", guide=False)
    ups = replay(session, order)
    assert list(session.base_T_ee) == order and sorted(ups[-1].frames) == sorted(order) and ups[-1].ee_T_cam
    with pytest.raises(Exception, match="fixed order"):
        replay(LiveSession(root, predictions="sim", guide=False), order + ["nope"])


def test_candidate_jackknife_equals_the_linearised_jackknife_of_the_graph_with_it(simulated):
    """Below 15 poses the few-pose cover (the leave-one-pose-out spread) is most of the total sigma
    on real arms, so the guide predicts it per candidate (guidance._jackknife_after, by Woodbury on each
    sample's downdated system) instead of shrinking it as n / (n + 1) for every candidate alike. The
    prediction must equal the linearised jackknife computed on the graph with the candidate's
    factors added, sample by sample, and candidates must differ in it."""
    from calib3r_graph.io.predictions import split_view_id
    from calib3r_graph.solver import guidance, plan
    from calib3r_graph.solver.jackknife import at_linear_minimum, factor_system, linearised_leave_one_out

    root = simulated(seed=5, frames=9, cameras=1, matches_per_pair=300)
    frames = load_dataset(root).frames
    session = LiveSession(root, predictions="sim", guide=False)
    for f in frames[:6]:
        session.add_frame(f)
    up = session.finish()  # solve's schedule: converged, so the candidate's zero residual is at the minimum
    sol = session.sol
    assert "cam0" in sol.stats.get("jackknife", {}), up.message
    offsets = factor_system(sol.graph, sol.values)[1]
    loo = guidance._leave_one_out(sol, 6)
    k_new = (gtsam.symbol("n", 0), gtsam.symbol("m", 0))
    covs = []
    for g in frames[6:]:
        E = session.poses_known[g]
        fs, vals, best, _ = plan.candidate_factors(sol, session.preds, session.engine.last_noise, E,
                                                   np.random.default_rng(0), keys_new=k_new,
                                                   points=plan.scene_points_by_view(sol))
        assert best is not None
        D, U = guidance._candidate_reduced(sol, fs, vals, offsets, k_new)
        predicted = guidance.jackknife_samples_after(sol, loo, D, U)["cam0"]
        before = guidance.jackknife_samples_after(sol, loo)["cam0"]
        graph, values = gtsam.NonlinearFactorGraph(sol.graph), gtsam.Values(sol.values)
        for f in fs:
            graph.add(f)
        for k in k_new:
            if vals.exists(k) and not values.exists(k):
                guidance._insert_like(values, vals, k)
        H, offs, factors = factor_system(graph, values)
        # the prediction takes the candidate's residual at its expectation, zero: so does this
        factors = factors[:-len(fs)] + [(ks, idx, AtA, 0 * Atb, 0.0) for ks, idx, AtA, Atb, _ in factors[-len(fs):]]
        system = at_linear_minimum((H, offs, factors))
        direct, _, _ = linearised_leave_one_out(graph, values, sol.keys, list(sol.base_T_cam), system)
        moved = 0.0
        for frame, dx in predicted.items():
            if frame == split_view_id(best)[1]:
                continue  # leaving out the view it overlaps strands the candidate's scale: no direct sample
            assert np.allclose(dx, direct[frame]["cam0"], rtol=1e-5, atol=1e-9), frame
            moved = max(moved, float(np.abs(dx - before[frame]).max()))
        assert moved > 1e-5  # the candidate changes the samples (1e-5 rad or m)
        covs.append(guidance._jackknife_after(sol, loo, D, U, 6)["cam0"])
    assert not np.allclose(covs[0], covs[1], rtol=0.05), "two candidates, one predicted jackknife"


def test_candidate_views_are_limited_to_the_viewpoint_change_the_pairs_span(simulated):
    """A candidate's scene factor is predicted only with views whose optical axis lies within the
    largest angle of the solution's verified pairs: a camera turned past it about the scene's
    centroid overlaps the scene (it is found with no limit) but is predicted to match nothing."""
    from calib3r_graph.solver import guidance, plan

    root = simulated(seed=5, frames=9, cameras=1, matches_per_pair=300)
    session = LiveSession(root, predictions="sim", guide=False)
    for f in load_dataset(root).frames[:6]:
        session.add_frame(f)
    sol, noise = session.sol, session.engine.last_noise
    limit = plan.matched_view_angle_deg(sol)
    axes = plan.view_axes(sol)
    pair_angles = [plan.axis_angle_deg(axes[o.view_a], axes[o.view_b]) for o in sol.observations]
    assert 1.0 < limit == max(pair_angles) < 90.0
    X = sol.ee_T_cam["cam0"]
    centroid, _ = guidance.scene_geometry(sol)
    views = list(sol.base_T_cam)

    def candidate(C, max_angle_deg=None):
        E = C.compose(X.inverse())
        return plan.candidate_factors(sol, session.preds, noise, E, np.random.default_rng(0),
                                      points=plan.scene_points_by_view(sol), max_angle_deg=max_angle_deg)

    # an existing view's own pose: within any limit, it overlaps
    assert candidate(sol.base_T_cam[views[0]])[2] is not None
    # turned about the centroid until every view is more than the limit away
    T0 = sol.base_T_cam[views[0]]
    axis = np.cross(T0.rotation().matrix()[:, 2], [0.0, 0.0, 1.0])
    for turn in np.arange(limit, limit + 40.0, 2.0):
        C = guidance._look_from(T0, centroid, axis, np.radians(turn))
        if min(plan.axis_angle_deg(axes[v], C.rotation().matrix()[:, 2]) for v in views) > limit + 2.0:
            break
    else:
        pytest.fail("no turn within 40 deg past the limit leaves every view beyond it")
    unlimited = candidate(C, max_angle_deg=180.0)
    assert unlimited[2] is not None and unlimited[3] >= plan.MIN_VISIBLE, unlimited[3]
    limited = candidate(C)
    assert limited[2] is None and len(limited[0]) == 1, (limit, turn)  # the robot factor alone


def test_distinct_points_are_numpys_unique_rows_and_counts():
    """plan.distinct_points (a lexsort of the columns, for speed) gives np.unique(axis=0)'s rows and
    counts: a view's points repeat once per pair that matched the same keypoint."""
    from calib3r_graph.solver.plan import distinct_points

    rng = np.random.default_rng(3)
    P = rng.normal(size=(2000, 3))
    P = np.r_[P, P[rng.integers(0, 2000, 1500)], P[:10] * [1, 1, -1]]  # repeats, and rows that differ in z only
    U, n = distinct_points({"v": rng.permutation(P), "empty": np.zeros((0, 3))})["v"]
    U_ref, n_ref = np.unique(P, axis=0, return_counts=True)
    assert np.array_equal(U, U_ref) and np.array_equal(n, n_ref) and n.sum() == len(P) and n.max() >= 2
    assert len(distinct_points({"empty": np.zeros((0, 3))})["empty"][0]) == 0


def test_stacked_visible_counts_are_each_views_own_projection(simulated):
    """plan.StackedPoints (every view's distinct points in the base frame, one projection per
    candidate, for speed) counts what each view's own projection counts, and candidate_factors picks
    the same overlapping view and visible points with it, at the poses the guide proposes."""
    from calib3r_graph.solver.guidance import candidate_poses
    from calib3r_graph.solver.plan import StackedPoints, candidate_factors, distinct_points, scene_points_by_view

    session = LiveSession(simulated(seed=5, frames=8, cameras=1, matches_per_pair=300), predictions="sim",
                          guide=False)
    replay(session, "recorded")
    sol, preds, noise = session.sol, session.preds, session.engine.last_noise
    points = scene_points_by_view(sol)
    distinct = distinct_points(points)
    stacked = StackedPoints.of(sol, preds, distinct)
    cands = candidate_poses(sol, dict(session.base_T_ee), 0.05, None, np.random.default_rng(0))
    assert len(cands) >= 10
    X = sol.ee_T_cam["cam0"]
    seen_some = 0
    for _, E in cands:
        C = E.compose(X)
        counts = stacked.visible_counts(C)
        for v, (U, n) in distinct.items():
            T = C.between(sol.base_T_cam[v])
            Q = U @ T.rotation().matrix().T + T.translation()
            K, (h, w) = preds.views[v].K, preds.views[v].depth.shape
            uv = Q[:, :2] / np.maximum(Q[:, 2:3], 1e-9) @ np.diag([K[0, 0], K[1, 1]]) + K[:2, 2]
            vis = (Q[:, 2] > 0.05) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            assert counts[v] == int(n[vis].sum())
            seen_some += 0 < counts[v] < n.sum()  # partly in view: the image bounds decide
        a = candidate_factors(sol, preds, noise, E, np.random.default_rng(1), points=points)  # every point projected
        b = candidate_factors(sol, preds, noise, E, np.random.default_rng(1), points=points, stacked=stacked)
        assert a[2:] == b[2:] and a[2] is not None
    assert seen_some > 0


def test_scoring_with_the_updates_information_matrix_equals_scoring_with_its_inverse(simulated):
    """An update hands the guidance its information matrix H with H^-1 (engine.last_information), so
    that the exact systematic re-scoring need not invert H^-1 again (14 % of the guidance's CPU on
    tabb_ds1's first 60 frames). H must be the inverse of the covariance it came with, and every
    candidate's score the same as with H inverted from H^-1."""
    from calib3r_graph.solver.guidance import candidate_poses, score_candidates

    root = simulated(seed=5, frames=9, cameras=1, matches_per_pair=300)
    session = LiveSession(root, predictions="sim", guide=False)
    for f in load_dataset(root).frames[:8]:
        up = session.add_frame(f)
    assert up.ee_T_cam, up.message
    S, offsets, H = session.engine.last_information
    assert np.abs(np.linalg.inv(S) - H).max() <= 1e-8 * np.abs(H).max()  # (cond(H) ~ 1e7 here)
    sol, base_T_ee = session.sol, session._dataset().base_T_ee
    cands = [(k, E, None) for k, E in candidate_poses(sol, base_T_ee, 0.05, None, np.random.default_rng(0))]
    assert len(cands) >= 10
    args = (sol, session.preds, session.engine.last_noise, base_T_ee, cands, 0.1, 0.01)
    given = score_candidates(*args, information=(S, offsets, H))
    inverted = score_candidates(*args, information=(S, offsets))
    assert [p.kind for p in given] == [p.kind for p in inverted]
    a, b = np.array([p.objective_after for p in given]), np.array([p.objective_after for p in inverted])
    assert np.allclose(a, b, rtol=1e-8) and len(set(np.round(a, 12))) > 1


def test_the_guide_counts_the_poses_the_solution_uses(simulated):
    """A frame whose views the solve left out adds no motion and no leave-one-out sample: the scores
    are those without it. At 13 used poses the next solve (14) still has its jackknife (below 15);
    with the unused frame counted as a 14th, the guide dropped the cover from every candidate's total
    (tabb_ds1, whose frontend leaves views out: its predicted sigma was 0.31 of what solve then
    reported at 15 frames, 0.98 since; bench/guide_prediction.py)."""
    from calib3r_graph.io.dataset import subset_dataset
    from calib3r_graph.io.predictions import load_predictions, subset_predictions
    from calib3r_graph.solver.guidance import score_candidates
    from calib3r_graph.solver.solve import SolveOptions, solve

    root = simulated(seed=5, frames=16, cameras=1, matches_per_pair=200)
    ds = load_dataset(root)
    preds = load_predictions(root, "sim", ds.cameras, set(ds.frames))
    used, rest = ds.frames[:13], ds.frames[13:]
    sol = solve(subset_dataset(ds, used), subset_predictions(preds, used),
                SolveOptions(progress=False, jackknife_method="linearised"))
    assert sol.stats.get("jackknife")
    sub_preds = subset_predictions(preds, used)
    cands = [("recorded", ds.base_T_ee[rest[0]], rest[0])]
    base = {f: ds.base_T_ee[f] for f in used}
    alone = score_candidates(sol, sub_preds, sol_noise(sol), base, cands, 1.0, 0.1)[0]
    # the 14th frame is in base_T_ee (the session has it) but none of its views is in the solution
    unused = score_candidates(sol, sub_preds, sol_noise(sol), {**base, rest[1]: ds.base_T_ee[rest[1]]}, cands,
                              1.0, 0.1)[0]
    assert unused.objective_after == pytest.approx(alone.objective_after, rel=1e-12)
    assert unused.sigma_after == alone.sigma_after


def sol_noise(sol):
    """The robot noise as the solve calibrated it (as `plan` and a live update hand the guide)."""
    import dataclasses

    from calib3r_graph.solver.graph import NoiseOptions

    mm, deg = sol.stats["noise_calibration"]["robot_sigma_used"]
    return dataclasses.replace(NoiseOptions(), robot_sigma_mm=mm, robot_sigma_deg=deg)
