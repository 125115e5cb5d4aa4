"""One live update's graph and the steps of ``solve`` on it (``UpdateContext``), what an update
carries to the next (``Calibration``), and an update's ``Solution`` whose GTSAM graph is built on
first use (``LiveSolution``). ``engine.py`` decides which steps an update takes; this module takes
them.

The update's linear system is linearised here by hand (:meth:`UpdateContext.linear_system`: the same
numbers as GTSAM's), reusing a pair's last linear factor where it still holds
(``linearisation.py``), and its step's cost is checked from the residuals the next weights need
anyway (:meth:`UpdateContext.error`). Per pair, what depends only on unchanged inputs is kept across
updates by identity (:meth:`UpdateContext.terms`, :meth:`UpdateContext.nominal_whitening`), so the
numbers are those a rebuild gives; a pair's whitening is kept within ``WHITENING_TOL``.
"""

import dataclasses
import functools
import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from calib3r_graph.errors import SolveError
from calib3r_graph.io.predictions import split_view_id
import calib3r_graph.live.linearisation as linearisation
from calib3r_graph.live.linearisation import PairLinearisation, point
from calib3r_graph.solver.camera_model import add_camera_model, camera_parameters, pair_sensitivities
from calib3r_graph.solver.graph import (MIN_FACTOR_MATCHES, add_depth_correction_priors, add_robot_factors,
                                        add_scale_gauge_factors, add_scene_factors, depth_correction, match_residuals,
                                        point_covariances, point_sqrt_info, robot_chi2, robot_views, scene_keys,
                                        scene_linearisation)
from calib3r_graph.solver.jackknife import cover, factor_system, linearised_jackknife, moved_system, wanted
from calib3r_graph.solver.solve import Solution, levenberg_marquardt, robust_weights
from calib3r_graph.solver.systematic import systematic_errors
from calib3r_graph.solver.uncertainty import (covariance_diagnostics, motion_diagnostics, noise_calibration,
                                              systematic_error_gain)
from factors.match3d import DEPTH_CORRECTION_DIM

log = logging.getLogger(__name__)

# A pair's whitening (point_sqrt_info) is kept while its relative rotation (rad) and depth-scale
# ratio (relative) stay within this of where it was computed (UpdateContext.nominal_whitening): W changes
# by about that fraction
WHITENING_TOL = 1e-3


@dataclass
class Calibration:
    """The noise calibration carried from update to update (uncertainty.noise_calibration)."""
    sigma0_sq: float = 1.0
    kappa: float = 1.0
    robot_factor: float = 1.0
    robot_fit: tuple | None = None


class LiveSolution(Solution):
    """An update's Solution whose ``graph`` is built on first use (``build_graph``: its builder, from
    :meth:`UpdateContext.deferred_graph`): the update itself needs only the graph's robot factors, the
    guidance the whole graph."""
    build_graph = None
    robot_graph = None  # the graph's robot, rigidity, gauge and prior factors (guidance._rescore_systematic)

    @property
    def graph(self):
        if self.__dict__.get("_graph") is None and self.build_graph is not None:
            self.__dict__["_graph"], self.build_graph = self.build_graph(), None
        return self.__dict__.get("_graph")

    @graph.setter
    def graph(self, graph):
        self.__dict__["_graph"] = graph


class UpdateContext:
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
        # the weights rule of a kept linearisation (linearisation.WEIGHT_TOL; None: off, the factor keeps
        # the weights it was linearised with, engine.KEEP_WEIGHTS_FROM)
        self.weight_tol = linearisation.WEIGHT_TOL
        self.linearised_at = None  # the values the last linear system was linearised at
        self.dropped = {}  # view -> why drop_weak left it out of this update
        self._camera_lins = None  # what the last linear system's camera-model terms are computed from
        self._robot_graph = None  # (values, calibration, views, robot_graph's graph)

    @property
    def sigmas(self) -> tuple:
        """The two noise options a pair's point covariances read (graph.point_covariances), which the
        per-pair caches compare."""
        return self.opt.noise.pixel_sigma_px, self.opt.noise.depth_sigma_rel

    def terms(self, values, observations=None) -> tuple[list, list]:
        """(match residuals, nominal whitening) per pair at ``values``, what ``robust_weights`` and the
        noise calibration take. Both depend only on the pair's observations, its two views' pose, depth
        scale and correction, and the noise options: a pair whose inputs are all equal to the cached
        ones (the views were not moved since) reuses them."""
        obs = self.observations if observations is None else observations
        noise = self.sigmas
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
                self.cache[(o.view_a, o.view_b)] = [o, of(o.view_a), of(o.view_b), noise, r, w, None]
        return res, W

    def whitened(self, values, observations=None) -> tuple[list, list, list]:
        """(match residuals, nominal whitening, whitened residuals ``W r`` (n, 3)) per pair at
        ``values``: :meth:`terms`, and ``W r`` computed once a pair and point and kept with them.
        The weights (:meth:`irls_weights`), the noise calibration and the step's cost check all read
        it (each whitened the residuals itself, 5-6 passes over every match an update; the same
        numbers)."""
        obs = self.observations if observations is None else observations
        res, W = self.terms(values, obs)
        white = []
        for o in obs:
            c = self.cache[(o.view_a, o.view_b)]  # (what terms returned: c[4], c[5])
            if c[6] is None:
                c[6] = np.einsum("nij,nj->ni", c[5], c[4])
            white.append(c[6])
        return res, W, white

    def irls_weights(self, values, conf, observations=None) -> list:
        """solve.robust_weights from the residuals at ``values``."""
        obs = self.observations if observations is None else observations
        res, W, white = self.whitened(values, obs)
        return robust_weights(obs, res, W, conf, whitened=white)

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
            for i, w in zip(old, self.irls_weights(values, [conf[i] for i in old], obs)):
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

    def robot_graph(self, values, calib):
        """:meth:`graph` without its scene factors (which alone read the weights), built once per
        values, calibration and views: a step's linear system, its cost check and the update's
        solution are built at the same point and read the same one (it was built three times an
        update)."""
        memo = self._robot_graph
        if memo is None or memo[0] is not values or memo[1] != calib or memo[2] is not self.views:
            memo = self._robot_graph = (values, calib, self.views, self.graph(values, None, calib, scene=False))
        return memo[3]

    def deferred_graph(self, values, weights, calib) -> tuple:
        """What :meth:`graph` builds the update's whole graph from: (values, weights, calibration, the
        pairs' whitening at values), kept rather than built. An update needs only its robot factors
        (the systematic part); its linear system comes from :meth:`linear_system`, which linearises
        the scene factors by hand. The whole graph, one GTSAM factor a pair (0.033 of a one-step
        update's 0.41 CPU s on rwhe_kuka_1), is built where the guidance asks for it
        (:class:`LiveSolution`); with reprojection factors, whose linearisation is GTSAM's, at once."""
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

        rest = self.robot_graph(values, calib)
        offsets = key_offsets(rest, values)  # the same keys as the whole graph's: every view has a robot or
        # rigidity factor, a gauge and (with a correction) a prior
        H, _, factors = factor_system(rest, values, offsets)
        noise, scale = self.noise(calib), 1.0 / (calib.sigma0_sq * calib.kappa)
        thetas, steps = camera_parameters(self.keys, self.ds.cameras, self.Ks) if camera else ([], [])
        sigmas, corr = self.sigmas, noise.depth_correction_sigma > 0
        lins, moved, W = [], {}, self.terms(values)[1]
        columns = lambda k: np.concatenate([np.arange(offsets[q][0], offsets[q][0] + offsets[q][1]) for q in k])  # noqa: E731
        for i, (o, w) in enumerate(zip(self.observations, weights)):
            pair = (o.view_a, o.view_b)
            kept = self.kept.get(pair)  # the pair's last linearisation, moved here where it holds (linearisation.py)
            m = None if self.fresh or kept is None or (thetas and kept.term is None) else kept.moved(
                o, w, scale, sigmas, values, self.keys, corr, self.weight_tol)
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
        e = self.robot_graph(at, calib).error(values)  # (its robot noise: at at's ee_T_cam)
        W_at, (r, W, white) = self.terms(at)[1], self.whitened(values)  # (the next weights read them too)
        for i, w in enumerate(weights):
            keep = w > 0
            if keep.sum() < MIN_FACTOR_MATCHES:  # no factor (add_scene_factors)
                continue
            # at's whitening, kept to values where the pair's hardly moved (nominal_whitening)
            wr = white[i][keep] if W_at[i] is W[i] else np.einsum("nij,nj->ni", W_at[i][keep], r[i][keep])
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
        keys, noise, sigmas = self.keys, self.opt.noise, self.sigmas
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

    def calibrate(self, values, weights) -> Calibration:
        """solve's noise calibration at ``values`` with the robust ``weights``."""
        grid = {v: self.preds.views[v].depth.shape[::-1] for v in self.views}
        residuals, whitening, white = self.whitened(values)
        sigma0_sq, kappa = noise_calibration(self.observations, residuals, whitening, weights, grid, whitened=white)
        chi2, dof = self.robot_fit(values)
        robot_factor = max(1.0, chi2 / max(dof, 1))
        if not np.isfinite(robot_factor):
            robot_factor = 1.0
        return Calibration(sigma0_sq, kappa, robot_factor, (chi2, dof))

    def robot_fit(self, values) -> tuple[float, int]:
        """(chi2, dof) of the robot poses at ``values`` under the nominal robot noise: the redundancy
        is 6 per frame less ee_T_cam and the world's similarity (13)."""
        chi2, n_frames = robot_chi2(self.keys, self.views, self.base_T_ee, values, self.opt.noise)
        return float(chi2), 6 * n_frames - 13

    def solution(self, graph, values, calib, history, timings, system=None) -> Solution:
        """``graph``: the graph, or what :meth:`deferred_graph` keeps to build it; ``system``: (H,
        offsets, factors) of that graph about ``values`` (factor_system), if already there."""
        keys, cameras, views = self.keys, self.cameras, self.views
        build = None
        if isinstance(graph, tuple):
            build = functools.partial(self.graph, *graph[:3], whitening=graph[3])
            graph = self.robot_graph(graph[0], graph[2])  # the robot factors: all the systematic part needs
        if system is None:
            system = self.linear_system(values, self.weights, calib)
        H, offsets, _ = system
        try:
            Hinv = np.linalg.inv(H)
        except np.linalg.LinAlgError:
            raise SolveError("the calibration is not observable from these frames yet") from None
        self.information = (Hinv, offsets, H)  # (H too: the guidance's exact re-scoring needs it)
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
        sol = LiveSolution(ee_T_cam={c: values.atPose3(keys.hand_eye(c)) for c in cameras}, covariance=covariance,
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
