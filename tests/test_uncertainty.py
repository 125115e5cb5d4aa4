"""Uncertainty: observability diagnostics, noise calibration, next best pose."""

import gtsam
import numpy as np
import pytest

from calib3r_graph.solver.uncertainty import (covariance_diagnostics, motion_diagnostics, noise_calibration,
                                      systematic_error_gain)


def poses_about_axis(axis, n=8, rng=None):
    rng = rng or np.random.default_rng(0)
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return {f"{i:04d}": gtsam.Pose3(gtsam.Rot3.Expmap(axis * rng.uniform(-1, 1)), rng.normal(size=3) * 0.2)
            for i in range(n)}


def test_parallel_rotation_axes_are_reported_with_the_axis():
    msgs = motion_diagnostics(poses_about_axis([0, 0, 1]), [f"{i:04d}" for i in range(8)])
    assert any("parallel" in m and "[0.00 0.00 1.00]" in m for m in msgs), msgs


def test_diverse_rotations_give_no_warning():
    rng = np.random.default_rng(1)
    poses = {f"{i:04d}": gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.5), rng.normal(size=3) * 0.2)
             for i in range(10)}
    assert motion_diagnostics(poses, list(poses)) == []


def test_systematic_error_gain_names_the_weak_direction():
    """Rotations of +-20 deg about ee x and only +-3 deg about ee y and z leave t_X along x
    fixed by the small rotations alone (tabb_ds1's motion is like this about its ee y)."""
    rng = np.random.default_rng(2)
    poses = {f"{i:04d}": gtsam.Pose3(gtsam.Rot3.Expmap(np.radians(rng.uniform(-1, 1, 3) * [20, 3, 3])),
                                     rng.normal(size=3) * 0.2) for i in range(30)}
    gain, axis = systematic_error_gain(poses, list(poses))
    # Brute force over pairs gives the same gain.
    M = np.vstack([poses[a].between(poses[b]).rotation().matrix() - np.eye(3)
                   for i, a in enumerate(poses) for b in list(poses)[i + 1:]])
    lam, V = np.linalg.eigh(M.T @ M / (len(M) // 3))
    assert gain == pytest.approx(1 / np.sqrt(lam[0]), rel=1e-9)
    assert abs(axis[0]) > 0.99 and gain > 10
    msgs = motion_diagnostics(poses, list(poses))
    assert any("ee direction [1.00 0.0" in m and "systematic" in m for m in msgs), msgs


def test_too_little_rotation_and_too_few_poses():
    poses = {f"{i}": gtsam.Pose3(gtsam.Rot3.Expmap([0.01 * i, 0, 0]), np.array([0.1 * i, 0, 0])) for i in range(4)}
    msgs = motion_diagnostics(poses, list(poses))
    assert any("only 4 robot poses: the sigma is not checked" in m and "11-43 %" in m for m in msgs)
    assert any("less than 10 degrees" in m for m in msgs)


def test_weak_direction_is_named_in_the_ee_frame():
    cov = np.diag([1e-8] * 3 + [1e-8, 1e-8, (5e-3) ** 2])  # 5 mm along cam z
    X = gtsam.Pose3(gtsam.Rot3.Rx(np.pi / 2), np.zeros(3))  # cam z = -ee y
    msgs = covariance_diagnostics("cam0", X, cov)
    assert len(msgs) == 1 and "translation" in msgs[0] and "[0.00 1.00 0.00]" in msgs[0] and "5.00 mm" in msgs[0]


def test_noise_calibration_recovers_variance_and_detects_correlation():
    from calib3r_graph.solver.observations import PairObservations

    rng = np.random.default_rng(0)
    n = 4000
    uv = rng.uniform([0, 0], [320, 240], size=(n, 2))
    obs = PairObservations("a/0", "b/0", uv, uv, np.ones((n, 3)), np.ones((n, 3)), np.ones(n),
                           np.zeros((n, 0)), np.zeros((n, 0)))
    W = np.broadcast_to(np.eye(3), (n, 3, 3))
    white = rng.normal(scale=0.5, size=(n, 3))
    s2, kappa = noise_calibration([obs], [white], [W], [np.ones(n)], {"a/0": (320, 240)})
    assert s2 == pytest.approx(0.25, rel=0.05) and kappa == pytest.approx(1.0, abs=0.3)
    # A smooth error shared by neighbours (one value per image cell) is what the design effect sees.
    cell = (uv[:, 0] // 40).astype(int) * 10 + (uv[:, 1] // 40).astype(int)
    smooth = rng.normal(scale=0.5, size=(100, 3))[cell]
    s2, kappa = noise_calibration([obs], [white + smooth], [W], [np.ones(n)], {"a/0": (320, 240)})
    assert s2 == pytest.approx(0.5, rel=0.1) and kappa > 10


@pytest.mark.slow
def test_plan_prefers_informative_candidates():
    """A pose near the recorded ones, turned 13 deg, lowers the expected total sigma; one 1 m above
    the table looking up sees no point of the scene and changes nothing (not even the motion's
    systematic gain or the few-pose cover: a view that overlaps nothing gives the solve nothing)."""
    from calib3r_graph.io.dataset import load_dataset
    from calib3r_graph.io.predictions import load_predictions
    from calib3r_graph.io.results import uncertainty_report
    from calib3r_graph.solver.graph import NoiseOptions
    from calib3r_graph.solver.guidance import objective, scene_geometry, score_candidates
    from calib3r_graph.solver.solve import SolveOptions, solve
    from tests.conftest import SAMPLE

    ds = load_dataset(SAMPLE)
    preds = load_predictions(SAMPLE, "sim", ds.cameras, set(ds.frames))
    sol = solve(ds, preds, SolveOptions(progress=False))
    E = ds.base_T_ee["0002"]
    cands = [("file", E.compose(gtsam.Pose3(gtsam.Rot3.Expmap([0.2, -0.1, 0.1]), np.array([0.01, 0.0, 0.0]))), "near"),
             ("file", gtsam.Pose3(gtsam.Rot3.Rx(np.pi / 2), np.array([0.0, 0.0, 1.0])), "away")]
    ranked = score_candidates(sol, preds, NoiseOptions(), ds.base_T_ee, cands, 1.0, 0.1)
    by = {c.frame: c for c in ranked}
    assert ranked[0].frame == "near" and by["near"].visible_points > 100 and by["near"].gain > 0.05
    now = objective(sol.covariance, sol.ee_T_cam, {c: sol.metric_scale[c][1] / abs(sol.metric_scale[c][0])
                                                   for c in sol.ee_T_cam}, float(np.median(scene_geometry(sol)[1])),
                    1.0, 0.1)
    assert by["away"].visible_points == 0 and by["away"].objective_after == pytest.approx(now, rel=1e-3)
    # the sigma after "near" is below the current one on the axis the current one is largest
    cur = {c: uncertainty_report(X, sol.covariance[c])["sigma_ee_frame"] for c, X in sol.ee_T_cam.items()}
    assert max(s["x_mm"] + s["y_mm"] + s["z_mm"] for s in by["near"].sigma_after.values()) < \
        max(s["x_mm"] + s["y_mm"] + s["z_mm"] for s in cur.values())


@pytest.mark.slow
def test_jackknife_agrees_with_the_reported_covariance_on_simulated_data(simulated):
    """Leave-one-pose-out spread vs the reported sigma: within a factor ~2.5 (a jackknife over
    12 poses is itself noisy), and written per camera."""
    from calib3r_graph.io.dataset import load_dataset
    from calib3r_graph.io.predictions import load_predictions
    from calib3r_graph.solver.jackknife import jackknife
    from calib3r_graph.solver.solve import SolveOptions, solve

    root = simulated(seed=61, frames=12)
    ds = load_dataset(root)
    preds = load_predictions(root, "sim", ds.cameras, set(ds.frames))
    opt = SolveOptions(progress=False, jackknife="never")  # the modelled covariance, to be checked
    sol = solve(ds, preds, opt)
    jk = jackknife(ds, preds, opt, sol, solve, progress=False)[0]["cam0"]
    assert jk["solves"] == 12
    ratio = np.array(jk["ratio_to_reported"])
    assert np.all(ratio > 0.3) and np.all(ratio < 2.5), ratio
    assert 0.5 < np.exp(np.mean(np.log(ratio))) < 2.0


@pytest.mark.slow
def test_plan_cli(tmp_path, capsys):
    import json

    from calib3r_graph.cli import main
    from calib3r_graph.io.dataset import read_robot_poses, write_robot_poses
    from tests.conftest import SAMPLE

    bad = tmp_path / "bad.csv"
    bad.write_text("frame,x\n")
    assert main(["plan", str(SAMPLE), "--candidates", str(bad), "--out", str(tmp_path / "o")]) == 3
    assert "bad.csv: row 1: header" in capsys.readouterr().err
    poses = read_robot_poses(SAMPLE / "robot_poses.csv")
    cands = {"c1": poses["0001"].compose(gtsam.Pose3(gtsam.Rot3.Rz(0.3), np.zeros(3))),
             "c2": poses["0005"].compose(gtsam.Pose3(gtsam.Rot3.Rx(0.2), np.array([0.02, 0, 0])))}
    good = tmp_path / "cands.csv"
    write_robot_poses(good, cands)
    assert main(["-q", "plan", str(SAMPLE), "--candidates", str(good), "--out", str(tmp_path / "o")]) == 0
    plan = json.loads((tmp_path / "o" / "plan.json").read_text())
    ranking = plan["ranking"]
    assert {r["frame"] for r in ranking} == {"c1", "c2"} and {r["kind"] for r in ranking} == {"file"}
    after = [r["objective_after"] for r in ranking]
    assert after == sorted(after) and ranking[0]["objective_gain"] > 0
    assert ranking[0]["largest_sigma_after_mm"] < plan["now_largest_sigma_mm_deg"][0]
    written = read_robot_poses(tmp_path / "o" / "next_poses.csv")
    assert list(written) == [r["frame"] for r in ranking]
    assert np.allclose(written[ranking[0]["frame"]].matrix(), ranking[0]["base_T_ee"], atol=1e-8)
    # without --candidates the guide makes its own, inside the visited region grown by --margin-m
    assert main(["-q", "plan", str(SAMPLE), "--next", "3", "--out", str(tmp_path / "g")]) == 0
    own = read_robot_poses(tmp_path / "g" / "next_poses.csv")
    assert list(own) == ["next01", "next02", "next03"]
    p = np.array([T.translation() for T in poses.values()])
    for T in own.values():
        assert np.all(T.translation() >= p.min(0) - 0.05 - 1e-9) and np.all(T.translation() <= p.max(0) + 0.05 + 1e-9)
    out = capsys.readouterr().out
    assert "next01" in out and "(8 poses; target 1.0 mm" in out  # 8 poses: the sigma is checked


def test_relative_rotations_equal_gtsam_logmap_up_to_a_half_turn():
    """The vectorised pairwise rotation vectors that check_motion, motion_diagnostics and
    guard.rotates_about_two_axes share, against gtsam's Logmap pair by pair, with a pair
    1e-5 rad short of a half turn, where the closed form alone loses the axis."""
    import gtsam

    from calib3r_graph.solver.uncertainty import relative_rotations

    rng = np.random.default_rng(0)
    poses = {f"{i:04d}": gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), np.zeros(3)) for i in range(12)}
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    poses["0100"] = gtsam.Pose3(gtsam.Rot3.Expmap(axis * (np.pi - 1e-5)), np.zeros(3))
    poses["0101"] = gtsam.Pose3()
    frames = list(poses)
    iu, ju = np.triu_indices(len(frames), 1)
    expected = [gtsam.Rot3.Logmap(poses[frames[i]].between(poses[frames[j]]).rotation()) for i, j in zip(iu, ju)]
    np.testing.assert_allclose(relative_rotations(poses, frames), expected, atol=1e-9)
