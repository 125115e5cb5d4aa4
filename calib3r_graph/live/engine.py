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
the new point while its linear model's predicted change is small and, below ``KEEP_WEIGHTS_FROM``
poses, its weights are within 1 % of those it was linearised with, and a pair's whitening while
its relative rotation and scale ratio stay within ``update.WHITENING_TOL``.

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
nominal whitening of pairs whose views did not move (:meth:`UpdateContext.terms`): the warm start of the
old views is the last solution, so the IRLS weights at the warm start, the graph's whitening and
the noise calibration reuse what the last update computed at its end. The points' covariances in
their own cameras are kept while a pair's observations are the same object, and a step's cost check
uses the residuals at its end that the next weights need anyway (:meth:`UpdateContext.error`).

An update's GTSAM graph is not built: its linear system is linearised by hand
(:meth:`UpdateContext.linear_system`), the systematic part needs only its robot factors, and the whole
graph, one factor a pair, is built where the guidance asks for ``sol.graph`` (:class:`LiveSolution`).

The covariance at every update comes from one linearisation (``jackknife.factor_system``): the
noise model's marginal (the inverse of the information matrix), the systematic part
(``systematic.py``, propagated through the same information matrix) and, below ``JACKKNIFE_BELOW`` poses, the cover of the linearised
leave-one-pose-out jackknife.
"""

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from calib3r_graph.errors import SolveError
from calib3r_graph.io.predictions import split_view_id
from calib3r_graph.live.update import Calibration, UpdateContext
from calib3r_graph.solver.graph import Keys
from calib3r_graph.solver.init import initialise, pairwise_sim3
from calib3r_graph.solver.jackknife import JACKKNIFE_BELOW
from calib3r_graph.solver.observations import build_observations
from calib3r_graph.solver.solve import MIN_ROBOT_POSES, Solution, SolveOptions

log = logging.getLogger(__name__)


# A total sigma beyond these is no calibration yet (a flange camera's mount offset is about 0.1 m; a
# 10 degree sigma is no rotation estimate): the update says "not observable yet" and the next starts
# cold rather than warm from it (require_calibration).
MAX_SIGMA_MM, MAX_SIGMA_DEG = 100.0, 10.0
# Nor is a metric scale whose sigma exceeds this fraction of it: its 2-sigma interval reaches zero.
# Measured (docs/live-notes.md, "A collapsed cold start"): rwhe_kuka_2's random order 15 started cold at
# 4 frames (two of them without a usable pair) in a degenerate minimum, three cameras at one centre
# and their views' scenes shrunk onto it, ee_T_cam 392 mm from the full result with a 28 mm sigma and
# the scale 0.00045 +- 0.032; every later update started warm from it and stayed 403-414 mm off for
# 20 frames (solve on those 4 frames says "not observable"). In 60 other replays of the four
# recordings the largest ratio was 0.27 (rwhe_kuka_2 at 3 frames), most below 0.01.
MAX_SCALE_REL = 0.5
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
# From this many poses a kept pair linearisation (linearisation.py) keeps the robust weights it was
# linearised with, where below it is refused once the weights given now moved by more than
# linearisation.WEIGHT_TOL; its observations, point sigmas and drift rule still decide. Every update's
# weights are lagged by one already (the IRLS runs one round per update); a kept factor's are lagged
# by the updates it is kept for. Where an update moves the estimate by less than its sigma (from
# JACKKNIFE_BELOW poses, the premise of the one-step updates) that changes neither the errors nor
# the cover. Measured (docs/live-notes.md, "Speed", session 24): rwhe_kuka_1's 20 random orders
# 3.14x -> 2.91x of their own solve in CPU, the same frames to 3 mm but one knife-edge order
# (3.00 -> 3.21 mm at 18 frames), the same 3-sigma cover; rwhe_kuka_2 and the simulator the same
# cover and median counts. Below it the weights move with the estimate: without the rule the
# few-pose re-runs rose from 6 to 10 on rwhe_kuka_1 (session 22).
KEEP_WEIGHTS_FROM = JACKKNIFE_BELOW
# A warm update whose robot fit grew by more than this F, the chi2 per new robot-residual dimension over
# the arm's variance the previous update measured (at least nominal; robot_fit_jump), is solved again from
# scratch (Engine._solve_again_cold): a warm path in a wrong minimum, where the scene agrees with itself and
# the robot no longer does. F = 100 is a 10-sigma residual, a gross error rather than the arm's noise.
# Measured over the 3,585 warm updates of 128 live replays (docs/live-notes.md, "A guard on the warm path, and LM that gave up"):
# F at most 19 where the update was sound (rwhe_kuka_1, whose robot has a systematic error; 4.8 on the
# simulator), 460 where rwhe_kuka_2's random order 19 lost the robot at 4 frames (142 mm from the full
# result, a robot variance factor of 656; from scratch 6 mm and 1.2). So is a warm update whose last step
# failed and whose LM then stayed at its start (Engine.stuck): its result is no solution (rwhe_kuka_2's
# random order 36 at 5 frames, F = 36, 36 mm off under a 17 mm sigma; once in 1,545 updates). Both were
# GTSAM's LM giving up at its damping bound, raised since (solve.LM_LAMBDA_UPPER), and now land well by
# themselves; the guard stays for a warm start in another basin.
LOST_ROBOT_F = 100.0


@dataclass
class State:
    base_T_cam: dict = field(default_factory=dict)  # view -> Pose3
    depth_scale: dict = field(default_factory=dict)  # view -> float
    correction: dict = field(default_factory=dict)  # view -> (K,)
    ee_T_cam: dict = field(default_factory=dict)  # camera -> Pose3
    calibration: Calibration = field(default_factory=Calibration)


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
        self.cold_restarts = 0  # warm updates solved again from scratch (LOST_ROBOT_F, stuck)
        self.started_cold, self.note = False, ""  # the last update's start, and what it did that a user should know
        self.stuck = False  # the last step of the last update: LM that made no iteration (Engine._last_step)

    # ------------------------------------------------------------------ one update
    def update(self, base_T_ee: dict, preds) -> Solution:
        """Solve with the frames of ``base_T_ee`` and their predictions, warm from the last update.
        A SolveError (not observable yet) leaves no state behind: the next update starts cold. A warm
        update that lost the robot (LOST_ROBOT_F) or could not move from its start (``stuck``) is solved
        again from scratch; ``note`` says so."""
        before = self.state.calibration.robot_fit if self.state is not None else None
        self.note = ""
        try:
            sol = self._update(base_T_ee, preds)
            jump = 0.0 if self.started_cold else robot_fit_jump(before, self.state.calibration.robot_fit)
            if LOST_ROBOT_F and jump > LOST_ROBOT_F:
                sol = self._solve_again_cold(base_T_ee, preds, sol,
                                             f"the warm update's new robot residual was {jump:.0f}x the arm's variance")
            elif not self.started_cold and self.stuck:
                sol = self._solve_again_cold(base_T_ee, preds, sol, "the warm update could not move from its start")
            self._last_cov = {c: np.asarray(C) for c, C in sol.covariance.items()}
            require_calibration(sol)
        except SolveError:
            self.state = None
            raise
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
        self.started_cold = cold
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
        ctx = UpdateContext(self.ds, base_T_ee, preds, observations, keys, Ks, views, cameras,
                            self.opt, self._terms, self._covariances, self._kept, self._whitening)
        if len(frames) >= KEEP_WEIGHTS_FROM:
            ctx.weight_tol = None
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
                weights = ctx.irls_weights(values, conf)
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
        new_weights = ctx.irls_weights(values, conf)
        next_calib = (ctx.calibrate(values, new_weights) if self.opt.noise_calibration
                      else Calibration(robot_fit=ctx.robot_fit(values)))
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

    def _solve_again_cold(self, base_T_ee, preds, warm, why) -> Solution:
        """The update solved again from scratch (solve's initialisation and schedule), taken where its
        robot chi2 is below the warm result's ``warm``; else the warm result, and the engine as it left it.
        Where the frames solved from scratch are no calibration yet (SolveError, require_calibration),
        neither is the warm result that the robot rejects: the SolveError is raised."""
        kept = (self.state, self.depth_ref, self._depth_of, self.last_noise, self.last_information)
        warm_chi2 = self.state.calibration.robot_fit[0]
        self.state = None
        self.cold_restarts += 1
        try:
            sol = self._update(base_T_ee, preds)
            require_calibration(sol)
        except SolveError as e:
            raise SolveError(f"{e}; solved again from scratch, as {why}") from None
        if self.state.calibration.robot_fit[0] < warm_chi2:
            self.note = (f"solved again from scratch: {why} (robot chi2 {warm_chi2:.3g} warm, "
                         f"{self.state.calibration.robot_fit[0]:.3g} from scratch)")
            log.info("%s", self.note)  # (the status line says it)
            return sol
        self.state, self.depth_ref, self._depth_of, self.last_noise, self.last_information = kept
        self.started_cold = False
        return warm

    def _schedule(self, ctx, values, conf, sims, history, weights=None, first=None):
        """solve's rounds from the warm placement, one Gauss-Newton step a round: the old pairs'
        first on IRLS weights at the warm start, the new pairs' on their RANSAC inliers, the
        re-weighted rounds, then the calibration for the last step (:meth:`_last_step`).
        Views the weights leave undetermined are left out as ``solve`` leaves them out
        (:meth:`UpdateContext.drop_weak`). ``weights``: the first round's instead; ``first``: the first round's
        optimiser instead of one step (the cold start's LM). (values, conf, weights, sims, calibration)."""
        weights, calib = ctx.warm_weights(values, conf, sims) if weights is None else weights, Calibration()
        ctx.fresh = True  # solve's own schedule: every pair linearised anew
        for rnd in range(self.opt.irls_rounds + 1):
            conf, weights, sims = ctx.drop_weak(values, conf, weights, sims)
            values = (first if rnd == 0 and first else ctx.step)(values, weights, calib, history)
            if rnd < self.opt.irls_rounds:
                weights = ctx.irls_weights(values, conf)
        conf, weights, sims = ctx.drop_weak(values, conf, weights, sims)
        calib = ctx.calibrate(values, weights) if self.opt.noise_calibration else Calibration()
        return values, conf, weights, sims, calib

    def _last_step(self, ctx, values, weights, calib, history):
        """The step whose linearisation serves the covariance: (values, its system moved to the step,
        what the graph it linearised is built from (:meth:`UpdateContext.deferred_graph`)), or LM to
        convergence where the step does not lower the cost (values, None, None)."""
        graph = ctx.deferred_graph(values, weights, calib)  # (before the step: the whitening cached is at values)
        stepped = ctx.gauss_newton(values, history, weights, calib)
        if stepped is None:
            values = ctx.lm(values, weights, calib, history)
            self.stuck = history[-1]["iterations"] == 0  # (the last step's: an earlier one's was replaced)
            return values, None, None
        self.stuck = False
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

        self.note = ""
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
        init = initialise(sorted(preds.views), observations, base_T_ee, "robot poses", seed=self.opt.seed)
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
        # residuals at the warm start (UpdateContext.warm_weights)
        new = [i for i, o in enumerate(observations)
               if o.view_a not in state.base_T_cam or o.view_b not in state.base_T_cam]
        for i, sim in zip(new, pairwise_sim3([observations[i] for i in new], seed=self.opt.seed)):
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


def require_calibration(sol):
    """Raise SolveError ("not observable from these frames yet") where an update's result is no
    calibration yet: a camera's largest total sigma beyond MAX_SIGMA_MM or MAX_SIGMA_DEG, or its
    metric scale not positive or with a sigma beyond MAX_SCALE_REL of it."""
    for c, X in sol.ee_T_cam.items():
        C = sol.covariance[c]
        sig_mm = np.sqrt(np.linalg.eigvalsh(C[3:, 3:])[-1]) * 1e3
        sig_deg = np.degrees(np.sqrt(np.linalg.eigvalsh(C[:3, :3])[-1]))
        if not (sig_mm < MAX_SIGMA_MM and sig_deg < MAX_SIGMA_DEG):
            raise SolveError(f"{c}: not observable from these frames yet (sigma {sig_mm:.3g} mm, {sig_deg:.3g} deg)")
        lam, sig_lam = sol.metric_scale[c]
        if not (lam > 0 and sig_lam < MAX_SCALE_REL * lam):
            raise SolveError(f"{c}: the metric scale is not observable from these frames yet ({lam:.3g} ± "
                             f"{sig_lam:.2g} m per depth unit)")


def robot_fit_jump(before, after) -> float:
    """How much worse the robot fits after an update than before: the growth of the robot chi2 per new
    residual dimension over the arm's variance measured before (chi2 per dof, at least the nominal 1),
    ``F = ((chi2_1 - chi2_0) / (dof_1 - dof_0)) / max(1, chi2_0 / dof_0)``; about 1 where the new poses
    agree with the rest. ``before``, ``after``: (chi2, dof) under the nominal robot noise, or None (0)."""
    if before is None or after is None or after[1] <= before[1] or before[1] < 1:
        return 0.0
    (c0, d0), (c1, d1) = before, after
    return float(((c1 - c0) / (d1 - d0)) / max(1.0, c0 / d0))


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

