"""The incremental engine: frames arrive one at a time, the calibration follows each.

Each update takes the predictions of the frames so far (``sources.py``: a recording's, or the
pairwise frontend run incrementally), places the new views, and takes **one Gauss-Newton step** on
the joint graph of ``solver/graph.py``, **warm-started from the previous solution**: the old views
start where they were, a new view from its best pairwise Sim(3) to a view already placed (the same
RANSAC + Umeyama as ``solve``'s initialisation). The step's linearisation also gives the covariance
and the linearised jackknife, so an update costs one linearisation (LM to convergence, three or
more); the iterations are spread over the updates, each starting where the last ended. A step that
does not lower the cost falls back to LM to convergence; the first solve (cold) runs ``solve``'s
schedule, LM to convergence from the initialisation in its first round and one Gauss-Newton step in
each later one, as the few-pose re-runs below (LM in every round cost 0.6 CPU s more at rwhe_kuka_1's
cold start, docs/live-notes.md). Why not iSAM2 (measured in docs/live.md): every update also changes the
weights of the *old* scene factors (robust re-weighting and the noise calibration rescale all of them) and
the pairwise frontend re-aggregates old views' depths when a new pair arrives, so iSAM2 would
have to remove and re-add most factors at every frame. What it saves, relinearising only what
moved, is done here per pair (``linearisation.py``): a pair's linear factor is kept and moved to
the new point while its weights are within 1 % of those it was linearised with and its linear
model's predicted change is small, and a pair's whitening while its relative rotation and scale
ratio stay within ``WHITENING_TOL``.

Robust re-weighting and noise calibration run at every update, lagged by one (an update whose one
step moves ee_T_cam by more than ``EXTRA_STEP_SIGMAS`` of its previous total sigma takes a second
step on the weights at its result, and one that still moves it by more than ``MOVE_SIGMAS`` runs
``solve``'s schedule instead, see ``_update``): the update's LM
uses the weights computed from the previous solution's residuals (new pairs: their RANSAC
inliers, as ``solve``'s first round) and the previous update's variance factors; after the LM
they are recomputed for the next update. The sequence of updates is thus the IRLS iteration
itself, one round per frame, at the cost of residuals only. Below ``JACKKNIFE_BELOW`` poses,
where a pose can move the estimate by more than its sigma and lagged weights then belong to
another solution, an update whose one step moved ee_T_cam by more than ``FEW_MOVE_SIGMAS`` of its
previous total sigma runs ``solve``'s schedule from the warm placement instead (measured in
docs/live.md: 8.7-12.1 mm against 1.1-3.2 mm from the full result at 6-9 poses of rwhe_kuka_1),
one Gauss-Newton step a round.
:meth:`Engine.finish` runs
``solve``'s schedule (its initialisation, two re-weighting rounds, then the noise-calibrated round),
so the final result is ``solve``'s on the same frames and predictions (see its docstring for why
not warm).

Per pair, what depends only on unchanged inputs is kept from the last update (by identity of the
inputs, so the numbers are those a rebuild gives; the kept linearisations and whitenings above are
the exceptions, within their tolerances): the observations of pairs whose matches and
views' predictions did not change (:meth:`Engine._observations`), and the match residuals and
nominal whitening of pairs whose views did not move (:meth:`_Context.terms`): the warm start of the
old views is the last solution, so the IRLS weights at the warm start, the graph's whitening and
the noise calibration reuse what the last update computed at its end. The points' covariances in
their own cameras are kept while a pair's observations are the same object, and a step's cost check
uses the residuals at its end that the next weights need anyway (:meth:`_Context.error`).

An update's GTSAM graph is not built: its linear system is linearised by hand
(:meth:`_Context.linear_system`), the systematic part needs only its robot factors, and the whole
graph, one factor a pair, is built where the guidance asks for ``sol.graph`` (:class:`_LiveSolution`).

The covariance at every update comes from one linearisation (``jackknife.factor_system``): the
noise model's marginal (the inverse of the information matrix), the systematic part
(``systematic.py``, propagated through the same information matrix) and, below ``JACKKNIFE_BELOW`` poses, the cover of the linearised
leave-one-pose-out jackknife.
"""

import dataclasses
import functools
import logging
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from calib3r_graph.errors import SolveError
from calib3r_graph.io.predictions import split_view_id
from calib3r_graph.solver.graph import (MIN_FACTOR_MATCHES, Keys, add_depth_correction_priors, add_robot_factors,
                                        add_scale_gauge_factors, add_scene_factors, depth_correction, match_residuals,
                                        point_covariances, point_sqrt_info, robot_chi2, robot_views,
                                        scene_keys, scene_linearisation)
from factors.match3d import DEPTH_CORRECTION_DIM
from calib3r_graph.solver.init import initialise, pairwise_sim3
from calib3r_graph.solver.jackknife import (JACKKNIFE_BELOW, cover, factor_system, linearised_jackknife, moved_system,
                                            wanted)
from calib3r_graph.solver.observations import build_observations
from calib3r_graph.solver.solve import (MIN_ROBOT_POSES, Solution, SolveOptions, levenberg_marquardt,
                                        robust_weights)
from calib3r_graph.solver.camera_model import add_camera_model, camera_parameters, pair_sensitivities
from calib3r_graph.live.linearisation import PairLinearisation, point
from calib3r_graph.solver.systematic import systematic_errors
from calib3r_graph.solver.uncertainty import (covariance_diagnostics, motion_diagnostics, noise_calibration,
                                              systematic_error_gain)

log = logging.getLogger(__name__)

# A total sigma beyond these is no calibration yet (a flange camera's mount offset is about 0.1 m; a
# 10 degree sigma is no rotation estimate): the update says "not observable yet" and the next starts
# cold rather than warm from it.
MAX_SIGMA_MM, MAX_SIGMA_DEG = 100.0, 10.0
# A one-step update (from JACKKNIFE_BELOW poses) that moves ee_T_cam by more than this many of the
# previous update's total sigma is re-run with solve's schedule (Engine._moved_far)
MOVE_SIGMAS = 3.0
# A one-step update (from JACKKNIFE_BELOW poses) that moves ee_T_cam by more than this many of the
# previous update's total sigma takes one more Gauss-Newton step on the weights re-computed at its
# result (Engine._update). Consistent data move an n-pose estimate by about its sigma / sqrt(n) per
# new pose (Mahalanobis over 6 axes: sqrt(chi2_6 / n), 1.22 at its 99.9 % quantile and n = 15), so a
# larger move says the step's weights, lagged by one update and with the new pairs' RANSAC inliers at
# full weight, belong to another solution. Measured on rwhe_kuka_2's guided orders (docs/live-notes.md): the
# update at 27 frames 2.52 and 2.38 sigma from solve on the same frames -> 0.62 and 0.61, one or two
# extra steps in 14 updates.
EXTRA_STEP_SIGMAS = 1.5
# Below JACKKNIFE_BELOW poses an update first takes the one step too, and runs solve's schedule from
# the warm placement only where that step moved ee_T_cam by more than this many of the previous
# update's total sigma (Engine._update): the schedule is there because with few poses each new pose
# moves the estimate by more than its sigma, so lagged weights belong to another solution; a
# measured move below one sigma says this pose did not. Measured on rwhe_kuka_2 at 9-14 poses:
# moves of 0.2-0.7 sigma; on rwhe_kuka_1's guided order 1.2-3.1 sigma at 6-13 poses (docs/live.md).
FEW_MOVE_SIGMAS = 1.0
# A pair's whitening (point_sqrt_info) is kept while its relative rotation (rad) and depth-scale
# ratio (relative) stay within this of where it was computed (_Context.nominal_whitening): W changes
# by about that fraction
WHITENING_TOL = 1e-3


@dataclass
class Calibration:
    """The noise calibration carried from update to update (uncertainty.noise_calibration)."""
    sigma0_sq: float = 1.0
    kappa: float = 1.0
    robot_factor: float = 1.0
    robot_fit: tuple | None = None


@dataclass
class State:
    base_T_cam: dict = field(default_factory=dict)  # view -> Pose3
    depth_scale: dict = field(default_factory=dict)  # view -> float
    correction: dict = field(default_factory=dict)  # view -> (K,)
    ee_T_cam: dict = field(default_factory=dict)  # camera -> Pose3
    calibration: Calibration = field(default_factory=Calibration)


class _LiveSolution(Solution):
    """An update's Solution whose ``graph`` is built on first use (``build_graph``: its builder, from
    :meth:`_Context.deferred_graph`): the update itself needs only the graph's robot factors, the
    guidance the whole graph."""
    build_graph = None
    robot_graph = None  # the graph's robot, rigidity, gauge and prior factors (plan._rescore_systematic)

    @property
    def graph(self):
        if self.__dict__.get("_graph") is None and self.build_graph is not None:
            self.__dict__["_graph"], self.build_graph = self.build_graph(), None
        return self.__dict__.get("_graph")

    @graph.setter
    def graph(self, graph):
        self.__dict__["_graph"] = graph


class Engine:
    """Incremental solver over a growing set of frames. ``opt``: ``solve``'s options."""

    def __init__(self, ds, opt: SolveOptions):
        self.ds = ds
        self.opt = dataclasses.replace(opt, progress=False)
        self.state: State | None = None
        self.depth_ref = {}  # view -> valid pixels of the depth map the state's depth scale refers to
        self._depth_of = {}  # view -> that depth map (unchanged maps are not compared again)
        self.last_noise, self.last_information = opt.noise, None
        # per-pair caches, keyed by (view_a, view_b): what depends only on inputs that did not change
        self._obs = {}  # -> (PairMatches, ViewPrediction a, ViewPrediction b, PairObservations or None)
        self._terms = {}  # -> (PairObservations, view a's values, view b's, noise, residuals, whitening)
        self._covariances = {}  # -> (PairObservations, (pixel sigma, depth sigma), their point_covariances)
        self._kept = {}  # -> linearisation.PairLinearisation: its last linearised factor, reused while it holds
        self._whitening = {}  # -> (PairObservations, sigmas, R_ab, s_b / s_a, its point_sqrt_info there)
        self._last_cov = {}  # camera -> the last update's total covariance of ee_T_cam
        self.extra_steps = 0  # one-step updates given a re-weighted second step (EXTRA_STEP_SIGMAS)
        self.far_moves = 0  # one-step updates re-run with solve's schedule (_moved_far)
        self.few_reruns = 0  # one-step updates below JACKKNIFE_BELOW poses re-run (FEW_MOVE_SIGMAS)

    # ------------------------------------------------------------------ one update
    def update(self, base_T_ee: dict, preds) -> Solution:
        """Solve with the frames of ``base_T_ee`` and their predictions, warm from the last update.
        A SolveError (not observable yet) leaves no state behind: the next update starts cold."""
        try:
            sol = self._update(base_T_ee, preds)
        except SolveError:
            self.state = None
            raise
        self._last_cov = {c: np.asarray(C) for c, C in sol.covariance.items()}
        for c, X in sol.ee_T_cam.items():
            C = sol.covariance[c]
            sig_mm = np.sqrt(np.linalg.eigvalsh(C[3:, 3:])[-1]) * 1e3
            sig_deg = np.degrees(np.sqrt(np.linalg.eigvalsh(C[:3, :3])[-1]))
            if not (sig_mm < MAX_SIGMA_MM and sig_deg < MAX_SIGMA_DEG):
                self.state = None
                raise SolveError(f"{c}: not observable from these frames yet (sigma {sig_mm:.3g} mm, {sig_deg:.3g} deg)")
        return sol

    def _update(self, base_T_ee: dict, preds) -> Solution:
        frames = {split_view_id(v)[1] for v in preds.views} & set(base_T_ee)
        if len(frames) < MIN_ROBOT_POSES:
            raise SolveError(f"only {len(frames)} robot pose(s) with predictions so far; the calibration needs "
                             f"{MIN_ROBOT_POSES}")
        timings = {}
        t = time.perf_counter()
        observations = self._observations(preds)
        if not observations:
            raise SolveError("no view pair has enough valid matches yet")
        timings["observations"] = time.perf_counter() - t
        t = time.perf_counter()
        cold = self.state is None or not set(self.state.ee_T_cam) >= {split_view_id(v)[0] for v in preds.views}
        if cold:
            _require_two_axes(base_T_ee, frames)
            state, inliers = self._cold(base_T_ee, preds, observations)
        else:
            state, inliers = self._warm(base_T_ee, preds, observations)
        timings["placement"] = time.perf_counter() - t
        views = sorted(state.base_T_cam)
        keep = [i for i, o in enumerate(observations) if o.view_a in state.base_T_cam and o.view_b in state.base_T_cam]
        observations = [observations[i] for i in keep]
        inliers = [inliers[i] for i in keep]
        cameras = [c for c in self.ds.cameras if any(split_view_id(v)[0] == c for v in views)]
        keys = Keys(views, cameras)
        Ks = {v: preds.views[v].K for v in views}
        ctx = _Context(self.ds, base_T_ee, preds, observations, keys, Ks, views, cameras,
                       self.opt, self._terms, self._covariances, self._kept, self._whitening)
        values = ctx.values(state)
        conf = [o.weight for o in observations]
        t = time.perf_counter()
        history = []
        # Below JACKKNIFE_BELOW poses each new pose moves the estimate by more than its noise
        # model's sigma, so weights lagged by one update are weights for another solution: on
        # rwhe_kuka_1's guided order, at 6-9 poses, the one-step warm path ended 8.7-12.1 mm from the
        # full result where `solve` on the same frames and predictions ends 0.9-1.6 mm from it, and
        # LM to convergence on the lagged weights did no better (9.4 mm at 6). There an update runs
        # solve's schedule from the warm placement, one Gauss-Newton step a round (1.1-3.2 mm; LM
        # to convergence in each round ended within 0.3 mm of that, for twice the time).
        few = len(frames) < JACKKNIFE_BELOW
        # From JACKKNIFE_BELOW poses the one step still makes single excursions where the new frame
        # moves the estimate far (rwhe_kuka_1, a random order: 4.1 mm at 16 poses, where solve on the
        # same frames and predictions is 0.3 mm from the full result and two more Gauss-Newton steps on
        # the same weights change nothing: the lagged weights belong to the previous solution, as
        # below 15). So a one-step result that moved ee_T_cam by more than MOVE_SIGMAS of the previous
        # update's own total sigma (inconsistent with it at 3 sigma) is re-run with solve's schedule
        # from the warm placement. Measured on ten replays of rwhe_kuka_1 (docs/live.md): 0-11 of the
        # 16 updates re-run, frames to stay within 3 mm median 18 -> 6.5, CPU of all updates +15 %.
        # Below JACKKNIFE_BELOW poses the one step is tried too, and kept where it moved ee_T_cam by
        # less than FEW_MOVE_SIGMAS of the previous total sigma (the schedule's premise, a pose that
        # moves the estimate by more than its sigma, measured rather than assumed from the count)
        start = values
        try_one = bool(few and FEW_MOVE_SIGMAS and self._last_cov)
        if cold:
            # solve's schedule: the first round on the RANSAC inliers with LM to convergence from the
            # initialisation, then one Gauss-Newton step a round (irls_rounds re-weighted rounds, then
            # the noise-calibrated round, _last_step), as the few-pose re-runs from a warm placement
            values, conf, weights, inliers, calib = self._schedule(
                ctx, values, conf, inliers, history, [o.weight * m for o, m in zip(observations, inliers)], ctx.lm)
        elif few and not try_one:
            values, conf, weights, inliers, calib = self._schedule(ctx, values, conf, inliers, history)
        else:
            weights, calib = ctx.warm_weights(values, conf, inliers), state.calibration
            conf, weights, inliers = ctx.drop_weak(values, conf, weights, inliers)
        values, system, graph = self._last_step(ctx, values, weights, calib, history)
        if not cold:
            if try_one and self._move(state, values, keys) > FEW_MOVE_SIGMAS:
                self.few_reruns += 1  # (start is what drop_weak left: it dropped views in place)
                values, conf, weights, inliers, calib = self._schedule(ctx, start, conf, inliers, history)
                values, system, graph = self._last_step(ctx, values, weights, calib, history)
            if not few and EXTRA_STEP_SIGMAS and self._move(state, values, keys) > EXTRA_STEP_SIGMAS:
                self.extra_steps += 1
                weights = robust_weights(ctx.observations, *ctx.terms(values), conf)
                conf, weights, inliers = ctx.drop_weak(values, conf, weights, inliers)
                for k in [k for k in start.keys() if not values.exists(k)]:  # the views it left out
                    start.erase(k)
                values, system, graph = self._last_step(ctx, values, weights, calib, history)
            if not few and MOVE_SIGMAS and self._moved_far(state, values, keys):
                values, conf, weights, inliers, calib = self._schedule(ctx, start, conf, inliers, history)
                values, system, graph = self._last_step(ctx, values, weights, calib, history)
        timings["optimisation"] = time.perf_counter() - t
        t = time.perf_counter()
        if system is None:
            graph = ctx.deferred_graph(values, weights, calib)
        ctx.weights = weights
        sol = ctx.solution(graph, values, calib, history, timings, system)
        self.last_noise, self.last_information = ctx.noise(calib), ctx.information  # for the guidance
        timings["covariance"] = time.perf_counter() - t
        # carried to the next update: the noise calibration at this solution, with the robust weights
        # the next update's IRLS starts from (its own residuals at the warm start)
        # (the residuals and whitening at this solution are kept per pair: the next update's warm start
        # of the pairs whose views did not move is this solution, so its warm_weights reuse them)
        t = time.perf_counter()
        res, W = ctx.terms(values)
        new_weights = robust_weights(ctx.observations, res, W, conf)
        next_calib = ctx.calibrate(values, new_weights, res, W) if self.opt.noise_calibration else Calibration()
        live = {(o.view_a, o.view_b) for o in ctx.observations}
        for cache in (self._terms, self._covariances, self._kept, self._whitening):
            for k in [k for k in cache if k not in live]:
                del cache[k]
        timings["next_weights"] = time.perf_counter() - t
        views = ctx.views  # (without the views drop_weak left out: the next update places them anew)
        self.state = State({v: sol.base_T_cam[v] for v in views}, dict(sol.depth_scale), dict(sol.depth_correction),
                           dict(sol.ee_T_cam), next_calib)
        self.depth_ref = {v: self.depth_ref[v] if self.depth_ref.get(v, (None, None, None))[2] is not None
                          and preds.views[v].depth is self._depth_of.get(v) else _valid_depth(preds.views[v].depth)
                          for v in views}
        self._depth_of = {v: preds.views[v].depth for v in views}
        return sol

    def _schedule(self, ctx, values, conf, sims, history, weights=None, first=None):
        """solve's rounds from the warm placement, one Gauss-Newton step a round: the old pairs'
        first on IRLS weights at the warm start, the new pairs' on their RANSAC inliers, the
        re-weighted rounds, then the calibration for the last step (:meth:`_last_step`).
        Views the weights leave undetermined are left out as ``solve`` leaves them out
        (:meth:`_Context.drop_weak`). ``weights``: the first round's instead; ``first``: the first round's
        optimiser instead of one step (the cold start's LM). (values, conf, weights, sims, calibration)."""
        weights, calib = ctx.warm_weights(values, conf, sims) if weights is None else weights, Calibration()
        ctx.fresh = True  # solve's own schedule: every pair linearised anew
        for rnd in range(self.opt.irls_rounds + 1):
            conf, weights, sims = ctx.drop_weak(values, conf, weights, sims)
            values = (first if rnd == 0 and first else ctx.step)(values, weights, calib, history)
            if rnd < self.opt.irls_rounds:
                weights = robust_weights(ctx.observations, *ctx.terms(values), conf)
        conf, weights, sims = ctx.drop_weak(values, conf, weights, sims)
        calib = ctx.calibrate(values, weights, *ctx.terms(values)) if self.opt.noise_calibration else Calibration()
        return values, conf, weights, sims, calib

    def _last_step(self, ctx, values, weights, calib, history):
        """The step whose linearisation serves the covariance: (values, its system moved to the step,
        what the graph it linearised is built from (:meth:`_Context.deferred_graph`)), or LM to
        convergence where the step does not lower the cost (values, None, None)."""
        graph = ctx.deferred_graph(values, weights, calib)  # (before the step: the whitening cached is at values)
        stepped = ctx.gauss_newton(values, history, weights, calib)
        if stepped is None:
            return ctx.lm(values, weights, calib, history), None, None
        return stepped[0], stepped[1], graph

    def _move(self, state, values, keys) -> float:
        """The largest move of an ee_T_cam since the previous update, in its previous total sigma
        (Mahalanobis)."""
        out = 0.0
        for c, X in state.ee_T_cam.items():
            C = self._last_cov.get(c)
            if C is None or not values.exists(keys.hand_eye(c)):
                continue
            d = gtsam.Pose3.Logmap(X.between(values.atPose3(keys.hand_eye(c))))
            out = max(out, float(np.sqrt(d @ np.linalg.solve(C, d))))
        return out

    def _moved_far(self, state, values, keys) -> bool:
        """Whether the one-step update moved some ee_T_cam by more than MOVE_SIGMAS of the previous
        update's total sigma."""
        if self._move(state, values, keys) > MOVE_SIGMAS:
            self.far_moves += 1
            return True
        return False

    def _observations(self, preds) -> list:
        """``build_observations`` of ``preds``, per pair from the cache where the pair's matches and both
        views' predictions are the same objects as last time (a recording's never change; the pairwise
        frontend hands back the same objects for the views whose aggregation did not change), so an
        update builds only its new or re-aggregated pairs. The same arrays as the batch's where a pair
        has at most ``max_matches_per_pair`` valid matches; above, the subsample is drawn from a
        generator of its own build (the batch draws all pairs from one)."""
        from calib3r_graph.io.predictions import Predictions

        cache, new = {}, []
        for p in preds.pairs:
            key, va, vb = (p.view_a, p.view_b), preds.views[p.view_a], preds.views[p.view_b]
            c = self._obs.get(key)
            if c is not None and c[0] is p and c[1] is va and c[2] is vb:
                cache[key] = c
            else:
                new.append(p)
        if new:
            built = {(o.view_a, o.view_b): o for o in build_observations(
                Predictions(preds.name, preds.info, preds.views, new), self.opt.max_matches_per_pair,
                seed=self.opt.seed)}
            for p in new:
                key = (p.view_a, p.view_b)
                cache[key] = (p, preds.views[p.view_a], preds.views[p.view_b], built.get(key))
        self._obs = cache
        return [cache[(p.view_a, p.view_b)][3] for p in preds.pairs if cache[(p.view_a, p.view_b)][3] is not None]

    def finish(self, base_T_ee: dict, preds) -> Solution:
        """The last update is ``solve`` itself on the same frames and predictions, so the result is
        ``solve``'s. Warm-starting it is not enough on real data: ``solve``'s two IRLS rounds do not
        reach a fixed point there (rwhe_kuka_1: each extra round moves ee x by about 0.5 sigma, 1.0
        sigma after six), so a warm path lands elsewhere on that path (0.48 sigma measured)."""
        from calib3r_graph.solver.solve import solve

        sol = solve(dataclasses.replace(self.ds, base_T_ee=dict(base_T_ee)), preds, self.opt)
        views = sorted(sol.base_T_cam)
        self.state = State({v: sol.base_T_cam[v] for v in views}, dict(sol.depth_scale), dict(sol.depth_correction),
                           dict(sol.ee_T_cam), Calibration(*_calibration_of(sol)))
        self.depth_ref = {v: _valid_depth(preds.views[v].depth) for v in views}
        self._depth_of = {v: preds.views[v].depth for v in views}
        used = sol.stats.get("noise_calibration", {}).get("robot_sigma_used")
        self.last_noise = (dataclasses.replace(self.opt.noise, robot_sigma_mm=float(used[0]),
                                               robot_sigma_deg=float(used[1])) if used else self.opt.noise)
        self.last_information = None
        return sol

    # ------------------------------------------------------------------ placement
    def _cold(self, base_T_ee, preds, observations):
        init = initialise(sorted(preds.views), observations, base_T_ee, "robot poses")
        state = State(dict(init.base_T_cam), dict(init.depth_scale), {}, dict(init.ee_T_cam))
        return state, [m if m is not None else np.zeros(len(o), bool) for o, m in zip(observations, init.inliers)]

    def _warm(self, base_T_ee, preds, observations):
        """The previous state, with re-aggregated views' depth scales carried over and each new view
        chained to a placed one by their pairwise Sim(3) (P_a ~ s R P_b + t, view a's units)."""
        old = self.state
        state = State(ee_T_cam=dict(old.ee_T_cam), calibration=old.calibration)
        for v, T in old.base_T_cam.items():
            if v not in preds.views:
                continue
            state.base_T_cam[v] = T
            same = preds.views[v].depth is self._depth_of.get(v)  # not re-aggregated: the same unit
            state.depth_scale[v] = old.depth_scale[v] * (1.0 if same else _unit_change(self.depth_ref.get(v),
                                                                                        preds.views[v].depth))
            state.correction[v] = old.correction.get(v)
        inliers = [None] * len(observations)
        # RANSAC only for the pairs with a view not placed yet; the others get IRLS weights from their
        # residuals at the warm start (_Context.carried_weight)
        new = [i for i, o in enumerate(observations)
               if o.view_a not in state.base_T_cam or o.view_b not in state.base_T_cam]
        for i, sim in zip(new, pairwise_sim3([observations[i] for i in new])):
            inliers[i] = sim
        while True:  # place the unplaced view with the strongest pair to a placed one, until none is left
            best = None
            for i in new:
                o, sim = observations[i], inliers[i]
                if sim is None or (o.view_a in state.base_T_cam) == (o.view_b in state.base_T_cam):
                    continue
                if best is None or sim[3].sum() > inliers[best][3].sum():
                    best = i
            if best is None:
                break
            o, (s, R, t, _) = observations[best], inliers[best]
            if o.view_a in state.base_T_cam:  # b from a: base_T_b = base_T_a (R, s_a t), s_b = s_a s
                s_a = state.depth_scale[o.view_a]
                state.base_T_cam[o.view_b] = state.base_T_cam[o.view_a].compose(gtsam.Pose3(gtsam.Rot3(R), s_a * t))
                state.depth_scale[o.view_b] = s_a * s
            else:  # a from b: b_T_a = (R^T, -R^T t s_b / s ... ) in metres
                s_b = state.depth_scale[o.view_b]
                s_a = s_b / s
                a_T_b = gtsam.Pose3(gtsam.Rot3(R), s_a * t)
                state.base_T_cam[o.view_a] = state.base_T_cam[o.view_b].compose(a_T_b.inverse())
                state.depth_scale[o.view_a] = s_a
        # per pair: its RANSAC Sim(3) (s, R, t, inliers) where a view was placed now; None: both were
        # placed before (or its RANSAC found nothing)
        return state, [sim if isinstance(sim, tuple) else None for sim in inliers]


def _calibration_of(sol) -> tuple:
    nc = sol.stats.get("noise_calibration", {})
    return (nc.get("variance_factor", 1.0), nc.get("design_effect", 1.0), nc.get("robot_variance_factor", 1.0),
            nc.get("robot_chi2_dof"))


def _require_two_axes(base_T_ee, frames):
    """Before a cold start: the flange must have rotated about two different axes (the rule of
    uncertainty.motion_diagnostics: the second singular value of the angle-weighted rotation axes at
    least 0.15 of the first), else LM only wanders in the unobservable directions."""
    from calib3r_graph.solver.uncertainty import relative_rotations

    w = relative_rotations(base_T_ee, sorted(frames))
    w = w[np.linalg.norm(w, axis=1) > np.radians(2)]
    if len(w) < 2:
        raise SolveError(f"the flange has not rotated yet ({len(frames)} poses): add poses rotated 30-90 degrees "
                         "about different axes")
    s = np.linalg.svd(w, compute_uv=False)
    if s[1] < 0.15 * s[0]:
        raise SolveError(f"the {len(frames)} poses so far rotate about one axis only: add poses that rotate about "
                         "a perpendicular axis")


def _unit_change(before, after) -> float:
    """How much a re-aggregated view's depth unit grew: median of after / before where both have depth
    (the pairwise frontend's unit is its reference pair's baseline, which a new pair may replace).
    ``before``: (flat indices, depths) of the previous depth map's valid pixels (sparse for that frontend)."""
    if before is None or before[2] != after.shape:
        return 1.0
    idx, d = before[0], before[1]
    a = after.ravel()[idx]
    ok = a > 0
    if ok.sum() < 10:
        return 1.0
    return float(1.0 / np.median(a[ok] / d[ok]))


def _valid_depth(depth):
    idx = np.flatnonzero(depth > 0)
    return idx, depth.ravel()[idx], depth.shape


class _Context:
    """What one update's graph is built from, and the steps of ``solve`` on it."""

    def __init__(self, ds, base_T_ee, preds, observations, keys, Ks, views, cameras, opt, cache=None,
                 covariances=None, kept=None, whitening=None):
        self.ds, self.base_T_ee, self.preds, self.observations = ds, base_T_ee, preds, observations
        self.keys, self.Ks, self.views, self.cameras, self.opt = keys, Ks, views, cameras, opt
        self.cache = {} if cache is None else cache
        self.covariances = {} if covariances is None else covariances  # pair -> (obs, sigmas, point_covariances)
        self.kept = {} if kept is None else kept  # pair -> linearisation.PairLinearisation
        self.whitening = {} if whitening is None else whitening  # pair -> (obs, sigmas, R_ab, ratio, W)
        # whether a linear system may reuse kept linearisations (linearisation.py): in an update's
        # first step only. A later step of the same update (the re-weighted second step, a re-run
        # of solve's schedule) follows a large move, where a factor linearised before it predicts
        # least well, and the schedule is to be solve's own (tests/test_live_few_poses.py: a re-run
        # with kept factors ended 0.14 sigma from solve's result, against 0.1 allowed)
        self.fresh = False
        self.linearised_at = None  # the values the last linear system was linearised at
        self.dropped = {}  # view -> why drop_weak left it out of this update
        self._camera_lins = None  # what the last linear system's camera-model terms are computed from

    def terms(self, values, observations=None) -> tuple[list, list]:
        """(match residuals, nominal whitening) per pair at ``values``, what ``robust_weights`` and the
        noise calibration take. Both depend only on the pair's observations, its two views' pose, depth
        scale and correction, and the noise options: a pair whose inputs are all equal to the cached
        ones (the views were not moved since) reuses them."""
        obs = self.observations if observations is None else observations
        noise = (self.opt.noise.pixel_sigma_px, self.opt.noise.depth_sigma_rel)
        sig = {}

        def of(v):
            if v not in sig:
                sig[v] = (values.atPose3(self.keys.pose(v)).matrix().tobytes(), values.atDouble(self.keys.scale(v)),
                          np.asarray(depth_correction(values, self.keys, v)).tobytes())
            return sig[v]

        res, W, todo = [None] * len(obs), [None] * len(obs), []
        for i, o in enumerate(obs):
            c = self.cache.get((o.view_a, o.view_b))
            if c is not None and c[0] is o and c[1] == of(o.view_a) and c[2] == of(o.view_b) and c[3] == noise:
                res[i], W[i] = c[4], c[5]
            else:
                todo.append(i)
        if todo:
            sub = [obs[i] for i in todo]
            for i, r, w in zip(todo, match_residuals(sub, values, self.keys), self.nominal_whitening(values, sub)):
                o = obs[i]
                res[i], W[i] = r, w
                self.cache[(o.view_a, o.view_b)] = (o, of(o.view_a), of(o.view_b), noise, r, w)
        return res, W

    def values(self, state) -> gtsam.Values:
        keys, values = self.keys, gtsam.Values()
        with_corr = self.opt.noise.depth_correction_sigma > 0
        for v in self.views:
            values.insert(keys.pose(v), state.base_T_cam[v])
            values.insert(keys.scale(v), float(state.depth_scale[v]))
            if with_corr:
                c = state.correction.get(v)
                values.insert(keys.correction(v), np.zeros(DEPTH_CORRECTION_DIM) if c is None else np.asarray(c))
        for cam in self.cameras:
            values.insert(keys.hand_eye(cam), state.ee_T_cam[cam])
            scales = [state.depth_scale[v] for v in self.views if split_view_id(v)[0] == cam]
            values.insert(keys.metric(cam), float(np.exp(np.mean(np.log(scales)))))
        return values

    def drop_weak(self, values, conf, weights, sims) -> tuple:
        """``solve``'s rule for a round (solver/views.unsupported_views): a view that no pair with
        three or more matches of non-zero weight determines (its pairs' weights all cut, say) leaves
        the update, its variables and its pairs with it, so that one weak view does not leave the
        information singular for all (rwhe_kuka_1, a random order: view 0020 so at 24-29 frames made
        four updates "not observable" and each next one a cold start). (conf, weights, sims) of the
        pairs left; the view is placed anew at the next update."""
        from calib3r_graph.solver.views import unsupported_views, without_views

        weak = unsupported_views(self.views, self.observations, weights)
        if not weak:
            return conf, weights, sims
        for v, reason in weak.items():
            log.info("live: %s: %s; this update goes on without it", v, reason)
            self.dropped[v] = reason
        self.views, self.cameras, self.observations, conf, weights, sims = without_views(
            set(weak), self.keys, values, self.views, self.cameras, self.observations, conf, weights, sims)
        return conf, weights, sims

    def warm_weights(self, values, conf, sims):
        """IRLS weights (solve.robust_weights) from the residuals at the warm start for the pairs of
        views placed before; for the pairs of a view placed now (``sims``: their RANSAC Sim(3)),
        confidence x RANSAC inliers."""
        old = [i for i, m in enumerate(sims) if m is None]
        out = [None if m is None else c * m[3] for c, m in zip(conf, sims)]
        if old:
            obs = [self.observations[i] for i in old]
            res, W = self.terms(values, obs)
            for i, w in zip(old, robust_weights(obs, res, W, [conf[i] for i in old])):
                out[i] = w
        return out

    def noise(self, calib):
        f = np.sqrt(calib.robot_factor)
        return dataclasses.replace(self.opt.noise, robot_sigma_mm=self.opt.noise.robot_sigma_mm * f,
                                   robot_sigma_deg=self.opt.noise.robot_sigma_deg * f)

    def graph(self, values, weights, calib, scene=True, whitening=None):
        """The update's graph; ``scene=False``: without its scene factors. ``whitening``: the pairs'
        :meth:`terms` whitening at ``values``, if already at hand."""
        keys, noise = self.keys, self.noise(calib)
        scale = 1.0 / (calib.sigma0_sq * calib.kappa)
        graph = gtsam.NonlinearFactorGraph()
        if scene:
            W = self.terms(values)[1] if whitening is None else whitening
            add_scene_factors(graph, keys, self.observations, [w * scale for w in weights], values, self.Ks, noise,
                              self.opt.reprojection, whitening=W)
        add_robot_factors(graph, keys, self.views, self.base_T_ee,
                          {c: values.atPose3(keys.hand_eye(c)) for c in self.cameras}, noise)
        add_scale_gauge_factors(graph, keys, self.views, noise)
        add_depth_correction_priors(graph, keys, self.views, noise)
        return graph

    def deferred_graph(self, values, weights, calib) -> tuple:
        """What :meth:`graph` builds the update's whole graph from: (values, weights, calibration, the
        pairs' whitening at values), kept rather than built. An update needs only its robot factors
        (the systematic part); its linear system comes from :meth:`linear_system`, which linearises
        the scene factors by hand. The whole graph, one GTSAM factor a pair (0.033 of a one-step
        update's 0.41 CPU s on rwhe_kuka_1), is built where the guidance asks for it
        (:class:`_LiveSolution`); with reprojection factors, whose linearisation is GTSAM's, at once."""
        at = (values, weights, calib, self.terms(values)[1])
        return self.graph(*at[:3], whitening=at[3]) if self.opt.reprojection else at

    def linear_system(self, values, weights, calib, camera=True) -> tuple:
        """:func:`factor_system` of :meth:`graph` with these weights and calibration at ``values``,
        its 3D match factors linearised here by hand (graph.scene_linearisation: the same numbers as
        GTSAM's), so that each pair's one Jacobian also gives its camera-model terms
        (:meth:`camera_terms`, for :meth:`solution`), consistent with H by construction. On rwhe_kuka_1's
        live updates at 15-30 poses this halved the camera model's cost (a second linearisation and
        a second Jacobian per pair, 0.27 s an update). The terms are computed from the kept Jacobians
        only when the solution asks for them, so a system that a second step replaces costs none.
        ``camera=False``: a step whose system serves no covariance (the few-pose schedule's
        re-weighting rounds) keeps nothing for them."""
        self.linearised_at, self._camera_lins = values, None
        if self.opt.reprojection:  # its reprojection factors are GTSAM's to linearise
            return factor_system(self.graph(values, weights, calib), values)
        from calib3r_graph.solver.systematic import key_offsets

        rest = self.graph(values, weights, calib, scene=False)
        offsets = key_offsets(rest, values)  # the same keys as the whole graph's: every view has a robot or
        # rigidity factor, a gauge and (with a correction) a prior
        H, _, factors = factor_system(rest, values, offsets)
        noise, scale = self.noise(calib), 1.0 / (calib.sigma0_sq * calib.kappa)
        thetas, steps = camera_parameters(self.keys, self.ds.cameras, self.Ks) if camera else ([], [])
        sigmas, corr = (self.opt.noise.pixel_sigma_px, self.opt.noise.depth_sigma_rel), noise.depth_correction_sigma > 0
        lins, moved, W = [], {}, self.terms(values)[1]
        columns = lambda k: np.concatenate([np.arange(offsets[q][0], offsets[q][0] + offsets[q][1]) for q in k])  # noqa: E731
        for i, (o, w) in enumerate(zip(self.observations, weights)):
            pair = (o.view_a, o.view_b)
            kept = self.kept.get(pair)  # the pair's last linearisation, moved here where it holds (linearisation.py)
            m = None if self.fresh or kept is None or (thetas and kept.term is None) else kept.moved(
                o, w, scale, sigmas, values, self.keys, corr)
            if m is not None:
                k = scene_keys(o, self.keys, noise)
                idx = columns(k)
                H[np.ix_(idx, idx)] += m[0]
                factors.append((k, idx) + m[:3])
                moved[i] = (kept,) + m[3:]
                lins.append(None)
                continue
            lin = scene_linearisation(o, w * scale, values, self.keys, self.Ks, noise, W[i])
            lins.append(lin if thetas else None)
            self.kept.pop(pair, None)
            if lin is None:
                continue
            k, _, _, J, e = lin
            idx = columns(k)
            AtA, Atb, btb = J.T @ J, -(J.T @ e), float(e @ e)
            H[np.ix_(idx, idx)] += AtA
            factors.append((k, idx, AtA, Atb, btb))
            self.kept[pair] = PairLinearisation(o, sigmas, point(o, values, self.keys, corr), np.array(w, float),
                                                scale, AtA, Atb, btb)
        if camera:
            self._camera_lins = (lins, values, noise, thetas, steps, moved)
        return H, offsets, factors

    def camera_terms(self):
        """The last linear system's camera-model terms per pair (camera_model.pair_sensitivities of its
        Jacobians; a reused linearisation's moved with it, linearisation.py), or None where it kept
        none (``camera=False``, or reprojection factors)."""
        if self._camera_lins is None:
            return None
        lins, values, noise, thetas, steps, moved = self._camera_lins
        out = pair_sensitivities(lins, values, self.keys, self.Ks, noise, thetas, steps)
        for i, (o, lin, t) in enumerate(zip(self.observations, lins, out)):
            if i in moved:
                kept, delta, r = moved[i]
                term = kept.moved_term(delta, r)
                out[i] = None if term is None else (scene_keys(o, self.keys, noise),) + term
                continue
            kept = self.kept.get((o.view_a, o.view_b))
            if lin is not None and kept is not None and kept.obs is o:  # (linearised in this system)
                kept.term = () if t is None else t[1:]
        return out

    def gauss_newton(self, values, history, weights, calib, camera=True):
        """One Gauss-Newton step from the warm start, on one linearisation that also serves the
        covariance and the jackknife: (values, that system moved to the step), or None when the step
        does not lower the cost. LM iterates to convergence within each update; here the iterations
        are spread over the updates (each update's step starts where the last ended), as the IRLS
        rounds are, and each update costs one linearisation instead of LM's three or more."""
        H, offsets, factors = self.linear_system(values, weights, calib, camera)
        self.fresh = True  # (the update's later steps linearise every pair anew)
        g = np.zeros(len(H))
        for _, idx, _, Atb, _ in factors:
            g[idx] += Atb
        e0 = 0.5 * sum(f[4] for f in factors)
        try:
            L = np.linalg.cholesky(H)
        except np.linalg.LinAlgError:
            return None
        dx = np.linalg.solve(L.T, np.linalg.solve(L, g))
        vv = gtsam.VectorValues()
        for k, (o, d) in offsets.items():
            vv.insert(k, dx[o:o + d])
        new = values.retract(vv)
        e1 = self.error(new, values, weights, calib)
        history.append({"round": len(history) + 1, "iterations": 1, "initial_error": e0, "final_error": e1,
                        "method": "gauss-newton step"})
        if not e1 <= e0:
            return None
        return new, moved_system((H, offsets, factors), dx)  # the same linear system about the new point

    def step(self, values, weights, calib, history):
        """One Gauss-Newton step on the graph with these weights (LM to convergence where it does not
        lower the cost)."""
        stepped = self.gauss_newton(values, history, weights, calib, camera=False)
        return self.lm(values, weights, calib, history) if stepped is None else stepped[0]

    def error(self, values, at, weights, calib) -> float:
        """The error of :meth:`graph` built at ``at`` (its scene factors' whitening is ``at``'s),
        evaluated at ``values``: the factors other than the scene's by GTSAM, the scene factors'
        0.5 |sqrt(w) W r|^2 from :meth:`terms` (the compressed factor's error is exactly that, so the
        same number to rounding). Its residuals at ``values`` are the ones the next round's weights
        and the next update's warm start need, so evaluating the step costs no pass of its own (the
        graph's error was a second pass over every match, with a GTSAM graph built for each round)."""
        scale = 1.0 / (calib.sigma0_sq * calib.kappa)
        e = self.graph(at, weights, calib, scene=False).error(values)  # (its robot noise: at at's ee_T_cam)
        for w, W, r in zip(weights, self.terms(at)[1], self.terms(values)[0]):
            keep = w > 0
            if keep.sum() < MIN_FACTOR_MATCHES:  # no factor (add_scene_factors)
                continue
            wr = np.einsum("nij,nj->ni", W[keep], r[keep])
            e += 0.5 * scale * float(w[keep] @ np.einsum("ni,ni->n", wr, wr))
        return e

    def lm(self, values, weights, calib, history):
        graph = self.graph(values, weights, calib)
        values, iters, e0, e1 = levenberg_marquardt(graph, values, self.opt.max_iterations, "live", False)
        history.append({"round": len(history) + 1, "iterations": iters, "initial_error": e0, "final_error": e1,
                        "matches_used": int(sum((w > 0).sum() for w in weights))})
        return values

    def nominal_whitening(self, values, observations=None):
        """Each pair's point_sqrt_info at ``values`` with unit weights. It depends on the pair's
        relative rotation and depth-scale ratio alone (view b's point covariances rotated and scaled
        into a's frame), so a pair's is kept while both are within ``WHITENING_TOL`` (rad, relative)
        of where it was computed: W then differs by about that fraction (the relative poses of
        rwhe_kuka_1's old pairs move by 1-4e-4 rad an update, linearisation.py). The point
        covariances in their own cameras, which do not depend on ``values``, are kept per pair
        across rounds and updates while the pair's observations are the same object and the two
        sigmas they read are equal (0.015 of a whitening pass's 0.039 CPU s over rwhe_kuka_1's 151
        pairs; the same numbers). Equal, not the same object: a session replaces the noise options
        at every update with the predictions' match noise, and an identity test missed every pair
        of every update."""
        keys, noise = self.keys, self.opt.noise
        sigmas = (noise.pixel_sigma_px, noise.depth_sigma_rel)  # all point_covariances reads of the noise
        out = []
        for o in (observations or self.observations):
            key = (o.view_a, o.view_b)
            R = values.atPose3(keys.pose(o.view_a)).rotation().between(values.atPose3(keys.pose(o.view_b)).rotation())
            ratio = values.atDouble(keys.scale(o.view_b)) / values.atDouble(keys.scale(o.view_a))
            w = self.whitening.get(key)
            if w is not None and w[0] is o and w[1] == sigmas and abs(ratio / w[3] - 1) <= WHITENING_TOL \
                    and np.linalg.norm(gtsam.Rot3.Logmap(w[2].between(R))) <= WHITENING_TOL:
                out.append(w[4])
                continue
            c = self.covariances.get(key)
            if c is None or c[0] is not o or c[1] != sigmas:
                c = (o, sigmas, point_covariances(o, self.Ks[o.view_a], self.Ks[o.view_b], noise))
                self.covariances[key] = c
            W = point_sqrt_info(o, self.Ks[o.view_a], self.Ks[o.view_b], gtsam.Pose3(R, np.zeros(3)), ratio, noise,
                                np.ones(len(o)), c[2])
            self.whitening[key] = (o, sigmas, R, ratio, W)
            out.append(W)
        return out

    def calibrate(self, values, weights, residuals, whitening) -> Calibration:
        """solve's noise calibration at ``values`` with the robust ``weights`` (``residuals`` and
        ``whitening``: :meth:`terms` at ``values``)."""
        grid = {v: self.preds.views[v].depth.shape[::-1] for v in self.views}
        sigma0_sq, kappa = noise_calibration(self.observations, residuals, whitening, weights, grid)
        chi2, n_frames = robot_chi2(self.keys, self.views, self.base_T_ee, values, self.opt.noise)
        robot_factor = max(1.0, chi2 / max(6 * n_frames - 13, 1))
        if not np.isfinite(robot_factor):
            robot_factor = 1.0
        return Calibration(sigma0_sq, kappa, robot_factor, (float(chi2), 6 * n_frames - 13))

    def solution(self, graph, values, calib, history, timings, system=None) -> Solution:
        """``graph``: the graph, or what :meth:`deferred_graph` keeps to build it; ``system``: (H,
        offsets, factors) of that graph about ``values`` (factor_system), if already there."""
        keys, cameras, views = self.keys, self.cameras, self.views
        build = None
        if isinstance(graph, tuple):
            build = functools.partial(self.graph, *graph[:3], whitening=graph[3])
            graph = self.graph(*graph[:3], scene=False)  # the robot factors: all the systematic part needs
        if system is None:
            system = self.linear_system(values, self.weights, calib)
        H, offsets, _ = system
        try:
            Hinv = np.linalg.inv(H)
        except np.linalg.LinAlgError:
            raise SolveError("the calibration is not observable from these frames yet") from None
        self.information = (Hinv, offsets)
        block = lambda k: Hinv[offsets[k][0]:offsets[k][0] + offsets[k][1], offsets[k][0]:offsets[k][0] + offsets[k][1]]
        covariance_model = {c: block(keys.hand_eye(c)) for c in cameras}
        if not all(np.all(np.isfinite(C)) and np.linalg.eigvalsh(0.5 * (C + C.T))[0] > 0
                   for C in covariance_model.values()):
            raise SolveError("the calibration is not observable from these frames yet (singular information)")
        robot = [(keys.hand_eye(split_view_id(v)[0]), keys.pose(v), self.base_T_ee[split_view_id(v)[1]])
                 for v in robot_views(keys, views)]
        # on the same information matrix (the update's one linearisation) rather than a second one
        systematic = systematic_errors(graph, values, robot, {c: (keys.hand_eye(c), keys.metric(c)) for c in cameras},
                                       system=(H, offsets))
        covariance = {c: covariance_model[c] + systematic[c].covariance for c in cameras}
        metric = {}
        for c in cameras:
            lam = values.atDouble(keys.metric(c))
            metric[c] = (lam, float(np.hypot(np.sqrt(block(keys.metric(c))[0, 0]), lam * systematic[c].scale_sigma_rel)))
        used_frames = {split_view_id(v)[1] for v in views}
        gain, axis = systematic_error_gain(self.base_T_ee, used_frames)
        stats = {"rounds": history, "timings_s": timings, "views_used": len(views),
                 "pairs_used": len(self.observations),
                 "noise_calibration": {"variance_factor": calib.sigma0_sq, "design_effect": calib.kappa,
                                       "robot_variance_factor": calib.robot_factor,
                                       "robot_chi2_dof": calib.robot_fit},
                 "systematic_error_gain": {"mm_per_mm": gain, "ee_direction": axis.tolist()},
                 "systematic": {c: systematic[c].to_json() for c in cameras}}
        sol = _LiveSolution(ee_T_cam={c: values.atPose3(keys.hand_eye(c)) for c in cameras}, covariance=covariance,
                       covariance_model=covariance_model, systematic=systematic, metric_scale=metric,
                       base_T_cam={v: values.atPose3(keys.pose(v)) for v in views},
                       depth_scale={v: values.atDouble(keys.scale(v)) for v in views},
                       depth_correction={v: depth_correction(values, keys, v) for v in views},
                       init_ee_T_cam={}, stats=stats,
                       views_dropped=[{"view": v, "reason": r} for v, r in self.dropped.items()],
                       diagnostics=motion_diagnostics(self.base_T_ee, used_frames),
                       graph=graph if build is None else None, values=values,
                       keys=keys, observations=self.observations,
                       scene_weight_scale=1.0 / (calib.sigma0_sq * calib.kappa))
        sol.build_graph, sol.robot_graph = build, graph if build is not None else None
        if wanted(self.opt.jackknife, len(used_frames)):
            jk, suspect = linearised_jackknife(sol, system)
            for c, rep in jk.items():
                before = np.asarray(sol.covariance[c])
                sol.covariance[c] = cover(before, np.asarray(rep["covariance"]))
                rep["covariance_before"] = before.tolist()
            sol.stats["jackknife"] = jk
            sol.stats["influential_pose"] = suspect
        for c in cameras:
            sol.diagnostics += covariance_diagnostics(c, sol.ee_T_cam[c], sol.covariance[c])
        # the intrinsics' own share where dataset.yaml states their sigma (solver/camera_model.py), as solve
        add_camera_model(sol, self.ds, [w * sol.scene_weight_scale for w in self.weights], self.Ks, self.noise(calib),
                         at=self.linearised_at, system=system, terms=self.camera_terms())
        return sol

