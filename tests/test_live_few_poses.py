"""Below JACKKNIFE_BELOW poses a live update whose one step moved ee_T_cam by more than
FEW_MOVE_SIGMAS of its previous total sigma runs solve's schedule from the warm placement
(live/engine.py): there a new pose can move the estimate by more than its noise sigma, and the
one-step warm path with weights lagged by one update ended 8.7-12.1 mm from rwhe_kuka_1's full
result where solve on the same frames ends 0.9-1.6 mm from it (docs/live.md). Each such update
must be solve's result on the frames so far; one that moved less keeps its one step."""

import dataclasses
import json

import gtsam
import numpy as np

from calib3r_graph.io.dataset import load_dataset, subset_dataset
from calib3r_graph.io.predictions import load_predictions, subset_predictions
from calib3r_graph.io.results import covariance_in_ee_frame
from calib3r_graph.live import LiveSession
from calib3r_graph.solver.solve import solve


def _z_to_solve(session, ds, preds, n) -> float:
    """The largest |z| of the session's estimate against solve on the first n frames: the session's
    options as they stand (its pixel sigma follows the predictions), z in solve's total sigma, the
    equivalence goal's (the linearised cover keeps the test short)."""
    opt = dataclasses.replace(session.engine.opt, jackknife_method="linearised")
    ref = solve(subset_dataset(ds, ds.frames[:n]), subset_predictions(preds, ds.frames[:n]), opt)
    X = session.sol.ee_T_cam["cam0"]
    d = gtsam.Pose3.Logmap(ref.ee_T_cam["cam0"].between(X))
    R = X.rotation().matrix()
    z = np.r_[R @ d[:3], R @ d[3:]] / np.sqrt(np.diag(covariance_in_ee_frame(X, ref.covariance["cam0"])))
    return float(np.abs(z).max())


def _nine_frame_replay(simulated, row) -> list:
    """``row(n, session, update, |z| to solve, the engine's few-pose re-runs before it)`` of each update
    with a result of a 9-frame simulated session."""
    root = simulated(seed=5, frames=9, cameras=1, matches_per_pair=300)
    ds = load_dataset(root)
    preds = load_predictions(root, "sim", ds.cameras, set(ds.frames))
    session = LiveSession(root, predictions="sim", guide=False)
    rows = []
    for n, f in enumerate(ds.frames, 1):
        before = session.engine.few_reruns
        up = session.add_frame(f)
        if up.ee_T_cam:
            rows.append(row(n, session, up, _z_to_solve(session, ds, preds, n), before))
    return rows


def _few_pose_replay(simulated):
    """(frames, re-run or not, |z| to solve) of each update of a 9-frame simulated session."""
    return _nine_frame_replay(simulated, lambda n, session, up, z, before: (n, session.engine.few_reruns > before, z))


def test_each_update_below_15_poses_that_reruns_is_solves_result_on_the_frames_so_far(simulated, monkeypatch):
    """With the threshold at zero every warm update below 15 poses re-runs with solve's schedule."""
    from calib3r_graph.live import engine as live_engine

    monkeypatch.setattr(live_engine, "FEW_MOVE_SIGMAS", 1e-9)
    rows = _few_pose_replay(simulated)
    assert [r for _, r, _ in rows] == [False] + [True] * (len(rows) - 1) and len(rows) >= 4, rows
    assert max(z for _, _, z in rows) < 0.1, rows


def test_an_update_below_15_poses_that_moves_less_than_its_sigma_keeps_its_one_step(simulated):
    """With the default threshold (one total sigma) the updates at 6 and 9 poses moved more and
    re-run; those at 7 and 8 keep their one step, measured 0.32 and 0.10 sigma from solve."""
    rows = _few_pose_replay(simulated)
    assert [(n, r) for n, r, _ in rows] == [(5, False), (6, True), (7, False), (8, False), (9, True)], rows
    assert all(z < 0.1 for _, r, z in rows if r), rows
    assert max(z for _, r, z in rows if not r) < 0.5, rows


def test_an_update_that_moves_far_runs_solves_schedule(simulated, monkeypatch):
    """From 15 poses a one-step update that moves ee_T_cam by more than MOVE_SIGMAS of the previous
    total sigma is re-run with solve's schedule (live/engine.py): with the threshold at zero every
    such update re-runs, and each must then be solve's result on the frames so far, as below 15."""
    from calib3r_graph.live import engine as live_engine

    monkeypatch.setattr(live_engine, "MOVE_SIGMAS", 1e-9)
    root = simulated(seed=5, frames=17, cameras=1, matches_per_pair=200)
    ds = load_dataset(root)
    preds = load_predictions(root, "sim", ds.cameras, set(ds.frames))
    session = LiveSession(root, predictions="sim", guide=False)
    worst = 0.0
    for n, f in enumerate(ds.frames, 1):
        session.add_frame(f)
        if n >= 15:
            worst = max(worst, _z_to_solve(session, ds, preds, n))
    assert session.engine.far_moves == 3 and worst < 0.1, (session.engine.far_moves, worst)


def test_an_update_that_moves_more_than_its_sigma_takes_a_reweighted_second_step(simulated, monkeypatch):
    """From 15 poses a one-step update that moves ee_T_cam by more than EXTRA_STEP_SIGMAS of the
    previous total sigma takes a second Gauss-Newton step on the weights re-computed at its result
    (live/engine.py). With the threshold at zero every such update takes it (and none is re-run
    with solve's schedule), and each lands closer to solve's result on the frames so far than the
    one step does. The updates below 15 poses all re-run with solve's schedule (FEW_MOVE_SIGMAS at
    zero), so that both start at 15 poses from solve's result on 14."""
    from calib3r_graph.live import engine as live_engine

    monkeypatch.setattr(live_engine, "FEW_MOVE_SIGMAS", 1e-9)
    root = simulated(seed=5, frames=17, cameras=1, matches_per_pair=200)
    ds = load_dataset(root)
    preds = load_predictions(root, "sim", ds.cameras, set(ds.frames))
    worst = {}
    for extra in (0.0, 1e-9):
        monkeypatch.setattr(live_engine, "EXTRA_STEP_SIGMAS", extra)
        session = LiveSession(root, predictions="sim", guide=False)
        worst[extra] = []
        for n, f in enumerate(ds.frames, 1):
            session.add_frame(f)
            if n >= 15:
                worst[extra].append(_z_to_solve(session, ds, preds, n))
        assert session.engine.far_moves == 0
        assert session.engine.extra_steps == (3 if extra else 0), session.engine.extra_steps
    # measured: 0.05-0.23 sigma from solve with one step (its linearisation partly kept, live/linearisation.py;
    # 0.11-0.21 with every pair linearised anew), 0.03-0.05 with the second
    assert all(b < a for a, b in zip(worst[0.0], worst[1e-9])) and max(worst[1e-9]) < 0.1, worst


def test_an_update_whose_metric_scale_is_undetermined_is_refused_and_the_next_starts_cold(simulated, monkeypatch):
    """An update whose metric scale is not positive, or whose sigma exceeds engine.MAX_SCALE_REL of
    it, is no calibration yet: rwhe_kuka_2 in a random order started cold at 4 frames in a collapsed
    minimum (ee_T_cam 392 mm off, the scale 0.00045 +- 0.032) and, warm from it, stayed 403-414 mm off
    for 20 updates (docs/live-notes.md). The rule on a well-determined simulated update, on that
    update's numbers, at the bound, and in a session: the refused update leaves no state, so the
    next one starts cold and is solve's result on its frames."""
    import pytest

    from calib3r_graph.errors import SolveError
    from calib3r_graph.live import engine as live_engine

    root = simulated(seed=5, frames=9, cameras=1, matches_per_pair=300)
    ds = load_dataset(root)
    preds = load_predictions(root, "sim", ds.cameras, set(ds.frames))
    session = LiveSession(root, predictions="sim", guide=False)
    for f in ds.frames[:6]:
        up = session.add_frame(f)
    assert up.ee_T_cam, up.message
    sol = session.sol
    lam, sig = sol.metric_scale["cam0"]
    assert 0 < sig < 0.01 * lam  # the simulator's scale is well determined at 6 poses
    live_engine.require_calibration(sol)
    for bad in [(4.47e-4, 0.032), (lam, 0.6 * lam), (-lam, sig)]:  # the collapsed start's; 2 sigma past zero; negative
        sol.metric_scale["cam0"] = bad
        with pytest.raises(SolveError, match="metric scale is not observable"):
            live_engine.require_calibration(sol)
    sol.metric_scale["cam0"] = (lam, 0.4 * lam)
    live_engine.require_calibration(sol)

    monkeypatch.setattr(live_engine, "MAX_SCALE_REL", 1e-9)  # every scale refused: this update's too
    up = session.add_frame(ds.frames[6])
    assert up.message.startswith("waiting: cam0: the metric scale is not observable") and not up.ee_T_cam
    assert session.engine.state is None
    monkeypatch.setattr(live_engine, "MAX_SCALE_REL", 0.5)
    up = session.add_frame(ds.frames[7])
    assert up.ee_T_cam, up.message
    assert _z_to_solve(session, ds, preds, 8) < 0.1  # cold: solve's schedule on the 8 frames


def test_below_five_poses_the_sigma_is_unchecked_and_the_session_is_never_done(simulated, tmp_path):
    """With 3 poses no pose can be left out to check the total sigma, with 4 only four can: on real
    recordings the error was outside 3 sigma in 33-67 % and 11-43 % of such calibrations
    (uncertainty.MIN_CHECKED_POSES). A target every update meets: the updates below 5 poses say the
    sigma is within it but unchecked, and the first from 5 poses is done."""
    from calib3r_graph.io.predictions import split_view_id
    from calib3r_graph.solver.uncertainty import MIN_CHECKED_POSES

    root = simulated(seed=5, frames=6, cameras=1, matches_per_pair=300)
    session = LiveSession(root, predictions="sim", guide=False, target_mm=1e3, target_deg=90.0, out=tmp_path)
    poses = []
    for f in load_dataset(root).frames:
        u = session.add_frame(f)
        if not u.ee_T_cam:
            continue
        poses.append(len({split_view_id(v)[1] for v in session.sol.base_T_cam}))
        if poses[-1] < MIN_CHECKED_POSES:
            assert not u.done and not u.sigma_checked and "too few to check it" in u.message, u.message
            assert "(unchecked)" in u.status_line()
        else:
            assert u.done and u.sigma_checked and "(unchecked)" not in u.status_line(), u.message
            break
    assert poses == [3, 4, 5], poses
    lines = [json.loads(x) for x in (tmp_path / "live.jsonl").read_text().splitlines()]
    assert [x["sigma_checked"] for x in lines if x["cameras"]] == [False, False, True]


def _restart_row(n, session, up, z, _) -> tuple:
    """(frames, |z| to solve, the engine's cold restarts so far, the update's message)."""
    return n, z, session.engine.cold_restarts, up.message


def _replay_with_a_lost_warm_update(simulated, monkeypatch, at=8):
    """(frames, |z| to solve, the engine's cold restarts, message) of each update of a
    9-frame simulated replay in which the warm path of the update at ``at`` frames lands in a wrong
    minimum: every step it takes returns ee_T_cam 30 mm and 3 degrees off (fault injection; the cold
    path and every other update are the engine's own)."""
    from calib3r_graph.live.engine import Engine

    wrong = gtsam.Pose3(gtsam.Rot3.Rz(np.radians(3.0)), np.array([0.03, 0.0, 0.0]))
    update, last_step = Engine._update, Engine._last_step

    def _update(self, base_T_ee, preds):
        self.inject = self.state is not None and len(base_T_ee) == at
        return update(self, base_T_ee, preds)

    def _last_step(self, ctx, values, weights, calib, history):
        values, system, graph = last_step(self, ctx, values, weights, calib, history)
        if self.inject:
            values = gtsam.Values(values)
            k = ctx.keys.hand_eye("cam0")
            values.update(k, values.atPose3(k).compose(wrong))
        return values, system, graph

    monkeypatch.setattr(Engine, "_update", _update)
    monkeypatch.setattr(Engine, "_last_step", _last_step)
    return _nine_frame_replay(simulated, _restart_row)


def test_a_warm_update_that_lost_the_robot_is_solved_again_from_scratch(simulated, monkeypatch):
    """A warm update whose robot fit grows by more than LOST_ROBOT_F (live/engine.py) is solved again
    from scratch, and the cold result is taken: the injected wrong minimum at 8 frames is replaced by
    solve's result on those frames, the message says so, and no other update restarts. Without the
    guard the same update stays in the wrong minimum (tens of sigma from solve)."""
    from calib3r_graph.live import engine as live_engine

    rows = _replay_with_a_lost_warm_update(simulated, monkeypatch)
    at8 = next(r for r in rows if r[0] == 8)
    assert at8[2] == 1 and "solved again from scratch" in at8[3], rows
    assert at8[1] < 0.5 and max(z for _, z, _, _ in rows) < 1.0, rows
    assert [r[2] for r in rows if r[0] < 8] == [0] * len([r for r in rows if r[0] < 8]), rows

    monkeypatch.undo()  # (the same injection again, not wrapped twice)
    monkeypatch.setattr(live_engine, "LOST_ROBOT_F", 0.0)
    rows = _replay_with_a_lost_warm_update(simulated, monkeypatch)
    at8 = next(r for r in rows if r[0] == 8)
    assert at8[2] == 0 and at8[1] > 10, rows



def test_a_warm_update_that_could_not_move_is_solved_again_from_scratch(simulated, monkeypatch):
    """A warm update whose last step failed and whose LM then made no iteration returns its own start,
    which is no solution (rwhe_kuka_2's random order 36 at 5 frames, docs/live-notes.md): it is solved
    again from scratch. Fault injection at 8 frames: the warm path's Gauss-Newton step fails and LM stays
    where it started, as GTSAM's does when no damping lowers the cost. (Its start there, the new view
    placed by its pairwise Sim(3), misfits the robot by F = 2992, so the robot-fit guard would fire
    first: it is off here.)"""
    from calib3r_graph.live import engine as live_engine
    from calib3r_graph.live.engine import Engine
    from calib3r_graph.live.update import UpdateContext

    on = {"warm at 8": False}
    update, gauss_newton, lm = Engine._update, UpdateContext.gauss_newton, UpdateContext.lm

    def _update(self, base_T_ee, preds):
        on["warm at 8"] = self.state is not None and len(base_T_ee) == 8
        return update(self, base_T_ee, preds)

    def _gauss_newton(self, values, history, *args, **kw):
        return None if on["warm at 8"] else gauss_newton(self, values, history, *args, **kw)

    def _lm(self, values, weights, calib, history):
        if not on["warm at 8"]:
            return lm(self, values, weights, calib, history)
        history.append({"round": len(history) + 1, "iterations": 0, "initial_error": 1.0, "final_error": 1.0})
        return values

    monkeypatch.setattr(live_engine, "LOST_ROBOT_F", 0.0)
    monkeypatch.setattr(Engine, "_update", _update)
    monkeypatch.setattr(UpdateContext, "gauss_newton", _gauss_newton)
    monkeypatch.setattr(UpdateContext, "lm", _lm)
    rows = _nine_frame_replay(simulated, _restart_row)
    assert [(n, c) for n, _, c, _ in rows] == [(5, 0), (6, 0), (7, 0), (8, 1), (9, 1)], rows
    at8 = rows[3]
    assert "could not move from its start" in at8[3] and at8[1] < 0.1, rows
