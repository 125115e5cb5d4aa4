"""A live update linearises its 3D match factors by hand (live/engine.py ``_Context.linear_system``,
graph.scene_linearisation), so that one Jacobian per pair serves the linear system and the camera
model's sensitivities. Both must be what GTSAM's linearisation and camera_model's own pass give,
at every update's linearisation point (non-zero residuals: real matches, moving estimates). The
step's cost check (``_Context.error``, from the residuals the update keeps) must be GTSAM's graph
error."""

import shutil

import numpy as np
import yaml

from calib3r_graph.live import LiveSession
from calib3r_graph.live import engine as live_engine
from calib3r_graph.solver.camera_model import camera_model_errors
from calib3r_graph.solver.jackknife import factor_system


def test_hand_linearisation_is_gtsams_and_serves_the_camera_model(simulated, tmp_path, monkeypatch):
    root = tmp_path / "sim"
    shutil.copytree(simulated(seed=5, frames=16, cameras=1, matches_per_pair=200), root)
    meta = yaml.safe_load((root / "dataset.yaml").read_text())
    meta["cameras"][0]["params_sigma"] = [2.0, 2.0, 3.0, 3.0]  # the camera-model share is propagated
    (root / "dataset.yaml").write_text(yaml.safe_dump(meta))

    systems, shares = [], []
    hand = live_engine._Context.linear_system

    def compared(ctx, values, weights, calib, camera=True):
        H, offsets, factors = hand(ctx, values, weights, calib, camera)
        graph = ctx.graph(values, weights, calib)
        H_ref, offsets_ref, factors_ref = factor_system(graph, values)
        assert offsets == offsets_ref
        g, g_ref = np.zeros(len(H)), np.zeros(len(H))
        for (_, idx, _, Atb, _), (_, idx_r, _, Atb_r, _) in zip(factors, factors_ref):
            g[idx] += Atb
            g_ref[idx_r] += Atb_r
        cost, cost_ref = sum(f[4] for f in factors), sum(f[4] for f in factors_ref)
        systems.append((float(np.abs(H - H_ref).max() / np.abs(H_ref).max()),
                        float(np.abs(g - g_ref).max() / np.abs(g_ref).max()), abs(cost - cost_ref) / cost_ref))
        if not camera:  # a re-weighting round's step: no camera terms asked for
            assert ctx.camera_terms() is None
            return H, offsets, factors
        scale = 1.0 / (calib.sigma0_sq * calib.kappa)
        cams = {c: ctx.ds.cameras[c] for c in ctx.cameras}
        args = (graph, values, ctx.keys, ctx.observations, [w * scale for w in weights], ctx.Ks, ctx.noise(calib),
                cams)
        shared = camera_model_errors(*args, system=(H, offsets), terms=ctx.camera_terms())
        own = camera_model_errors(*args, system=(H_ref, offsets_ref))
        shares.append((max(float(np.abs(shared[c].covariance - own[c].covariance).max()
                                 / np.abs(own[c].covariance).max()) for c in cams),
                       float(np.abs(own["cam0"].covariance).max())))
        return H, offsets, factors

    errors = []
    own_error = live_engine._Context.error

    def compared_error(ctx, values, at, weights, calib):
        e = own_error(ctx, values, at, weights, calib)
        e_ref = ctx.graph(at, weights, calib).error(values)  # the graph built at the step's start
        errors.append(abs(e - e_ref) / e_ref)
        return e

    # every update below 15 poses re-runs with the schedule, so that its steps are compared too
    monkeypatch.setattr(live_engine, "FEW_MOVE_SIGMAS", 1e-9)
    monkeypatch.setattr(live_engine._Context, "linear_system", compared)
    monkeypatch.setattr(live_engine._Context, "error", compared_error)
    session = LiveSession(root, predictions="sim", guide=False)
    for f in session.poses_known:
        session.add_frame(f)
    # the few-pose schedule (4 steps an update) and the one-step path from 15 poses both linearise here
    assert len(systems) >= 30 and len(shares) >= 10, (len(systems), len(shares))
    worst = np.max(np.array(systems), axis=0)
    assert np.all(worst < 1e-8), worst  # information, gradient, cost: the same numbers
    assert max(c[0] for c in shares) < 1e-8  # the camera-model share: the same
    assert len(errors) >= 30 and max(errors) < 1e-10, (len(errors), max(errors))  # the step's cost: GTSAM's
    assert min(c[1] for c in shares) > 0  # and not zero (the test would pass on no camera model)


def test_an_updates_graph_is_built_where_asked_and_is_the_one_its_step_linearised(simulated, monkeypatch):
    """An update keeps what its graph is built from (``_Context.deferred_graph``): the update itself
    needs only the robot factors; the guidance's first use of ``sol.graph`` builds the whole graph,
    the one the update's last step linearised (the same factors, the same error)."""
    last = {}
    hand = live_engine._Context.linear_system

    def kept(ctx, values, weights, calib, camera=True):
        if camera:  # the system a covariance is computed from
            last["args"] = (ctx, values, weights, calib)
        return hand(ctx, values, weights, calib, camera)

    monkeypatch.setattr(live_engine._Context, "linear_system", kept)
    session = LiveSession(simulated(seed=5, frames=16, cameras=1, matches_per_pair=200), predictions="sim",
                          guide=False)
    checked = []
    for f in session.poses_known:
        up = session.add_frame(f)
        if not up.ee_T_cam or up.message.startswith("waiting"):
            continue
        sol = session.sol
        assert sol.build_graph is not None and sol.__dict__.get("_graph") is None  # not built by the update
        graph = sol.graph
        assert sol.build_graph is None and sol.graph is graph  # built once
        ctx, values, weights, calib = last["args"]
        ref = ctx.graph(values, weights, calib)
        assert graph.size() == ref.size() > ctx.graph(values, weights, calib, scene=False).size()
        e, e_ref = graph.error(sol.values), ref.error(sol.values)
        assert abs(e - e_ref) <= 1e-12 * e_ref, (e, e_ref)
        checked.append(e)
    assert len(checked) >= 10 and min(checked) > 0, checked


def test_a_pairs_point_covariances_are_computed_once_while_its_matches_and_sigmas_stay(simulated, monkeypatch):
    """A pair's point covariances (its matches in their own cameras, from the pixel and depth sigmas)
    do not depend on the estimate, so an update computes them only for the pairs whose observations
    are new. The session sets the predictions' match noise into new noise options at every update;
    the cache once compared those by identity and missed every pair of every update (rwhe_kuka_1's
    recorded replay: all 168 pairs again at 30 frames). A changed sigma still recomputes them all."""
    import dataclasses

    calls = []
    own = live_engine.point_covariances
    monkeypatch.setattr(live_engine, "point_covariances",
                        lambda o, *a: calls.append((o.view_a, o.view_b)) or own(o, *a))
    session = LiveSession(simulated(seed=5, frames=16, cameras=1, matches_per_pair=200), predictions="sim",
                          guide=False)
    assert session.pixel_from_predictions
    engine, warm, frames = session.engine, [], list(session.poses_known)
    for f in frames[:-1]:
        kept = {k: c[0] for k, c in engine._covariances.items()}  # pair -> the observations they are of
        calls.clear()
        up = session.add_frame(f)
        if not up.ee_T_cam or up.message.startswith("waiting"):
            continue
        again = [k for k in calls if k in kept and engine._obs[k][3] is kept[k]]  # same matches, same sigmas
        assert not again, again
        warm.append((len(calls), len(engine._covariances)))
    assert len(warm) >= 8 and all(n < total for n, total in warm[2:]), warm
    for (a, b), (o, sigmas, (C_a, C_b)) in engine._covariances.items():  # what is kept is what it would compute
        assert sigmas == (engine.opt.noise.pixel_sigma_px, engine.opt.noise.depth_sigma_rel)
        K = session.preds.views
        F_a, F_b = own(o, K[a].K, K[b].K, engine.opt.noise)
        assert np.array_equal(C_a, F_a) and np.array_equal(C_b, F_b)
    session.pixel_from_predictions = False  # (else the next update sets the predictions' sigma back)
    engine.opt = dataclasses.replace(engine.opt, noise=dataclasses.replace(engine.opt.noise, pixel_sigma_px=0.7))
    calls.clear()
    up = session.add_frame(frames[-1])
    assert up.ee_T_cam and set(calls) == set(engine._covariances) and len(calls) == len(engine._covariances)
