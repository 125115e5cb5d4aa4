"""``solve``: predictions + robot poses -> hand-eye calibration, metric scale, trajectory.

Pipeline: load and validate -> lift matches to 3D -> initialise from the data ->
Levenberg-Marquardt on the joint graph, re-weighted between rounds (IRLS with a
Huber weight and a hard cut for gross outliers, so outlier matches do not bend the
result) -> marginal covariances -> outputs.
"""

import contextlib
import dataclasses
import logging
import sys
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from calib3r_graph.errors import SolveError
from calib3r_graph.io.dataset import Dataset
from calib3r_graph.io.predictions import Predictions, split_view_id
from calib3r_graph.solver.graph import (Keys, NoiseOptions, add_depth_correction_priors, add_robot_factors,
                                 add_scale_gauge_factors, add_scene_factors, depth_correction, initial_values,
                                 match_residuals, point_sqrt_info, robot_chi2, robot_views)
from calib3r_graph.solver.camera_model import add_camera_model
from calib3r_graph.solver.init import initialise
from calib3r_graph.solver.jackknife import cover, jackknife, wanted
from calib3r_graph.solver.observations import build_observations
from calib3r_graph.solver.systematic import systematic_errors
from calib3r_graph.solver.uncertainty import (check_motion, covariance_diagnostics, motion_diagnostics,
                                      noise_calibration, systematic_error_gain)
from calib3r_graph.solver.views import (dropped_by_frontend, pose_disagreements_kept, unsupported_views, view_words,
                                        without_views)

log = logging.getLogger(__name__)

# chi2(3) quantiles (scipy.stats.chi2.ppf(q, 3); written out, since importing scipy.stats takes ~1 s)
CHI2_3_MEDIAN = 2.3659738843753377  # q = 0.5
OUTLIER_CUT_CHI2 = 16.266236196238129  # q = 0.999: matches beyond this are dropped
HUBER_K = np.sqrt(7.814727903251178)  # q = 0.95


@dataclass
class SolveOptions:
    noise: NoiseOptions = field(default_factory=NoiseOptions)
    max_matches_per_pair: int = 2000
    irls_rounds: int = 2
    noise_calibration: bool = True  # variance factor x design effect on the scene factors (uncertainty.py)
    init: str = "predictions"  # "predictions": pairwise Sim(3) + spanning tree; "colmap": the frontend's poses
    progress: bool = True  # LM iterations on stderr
    max_iterations: int = 50
    reprojection: bool = False  # see factors/reprojection.py: double-counts the match noise
    seed: int = 0  # every random draw of a solve: the match subsample, the pairwise RANSAC, the closed form
    # leave-one-pose-out solves whose spread the total covariance must cover (jackknife.py):
    # "auto" below JACKKNIFE_BELOW robot poses, "always", "never"
    jackknife: str = "auto"
    # how: "resolve" (n re-solves) or "linearised" (a downdate of the solved graph per pose); None:
    # jackknife.METHOD ("resolve"; bench/jackknife.py measures the two)
    jackknife_method: str | None = None
    # processes for the re-solving jackknife's independent solves (jackknife.workers); None: every CPU
    jobs: int | None = None


@dataclass
class Solution:
    ee_T_cam: dict  # camera -> Pose3
    covariance: dict  # camera -> 6x6 total: model + systematic (rad, m; GTSAM Pose3 tangent order)
    metric_scale: dict  # camera -> (value, sigma)
    base_T_cam: dict  # view -> Pose3
    depth_scale: dict  # view -> metres per frontend unit
    depth_correction: dict  # view -> (K,) relative correction coefficients
    init_ee_T_cam: dict
    stats: dict
    views_dropped: list
    diagnostics: list = field(default_factory=list)  # observability warnings, plain words
    # The final graph, its solution and keys (for planning); not written anywhere.
    graph: object = field(default=None, repr=False)
    values: object = field(default=None, repr=False)
    keys: object = field(default=None, repr=False)
    observations: list = field(default_factory=list, repr=False)
    scene_weight_scale: float = 1.0
    covariance_model: dict = field(default_factory=dict)  # camera -> 6x6 marginal of the noise model alone
    systematic: dict = field(default_factory=dict)  # camera -> systematic.SystematicError
    camera_model: dict = field(default_factory=dict)  # camera -> camera_model.CameraModelError

    @property
    def frames(self) -> list:
        """The robot poses (frame ids, sorted) whose views the solution holds."""
        return sorted({split_view_id(v)[1] for v in self.base_T_cam})


# GTSAM's LM damps with lambda * I and gives up, returning where it started, once lambda passes its upper
# bound (1e5 by default) without lowering the cost. The whitened information here is far larger (a robot
# pose factor alone is 1 / (0.2 mm)^2 = 2.5e7 per m^2), so at 1e5 the damped step is still the full
# Gauss-Newton step, and a start where that step overshoots was returned unmoved: a live update on
# rwhe_kuka_2 (random order 36, 5 frames) reported its warm start, 36 mm off, as its result
# (docs/live-notes.md, "A guard on the warm path, and LM that gave up"). Up to 1e12 the step can shrink to the gradient's
# direction. The batch solves of the four recordings never reach 1e5: bit-identical results.
LM_LAMBDA_UPPER = 1e12


def levenberg_marquardt(graph, values, max_iterations, label, progress=True):
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-6)
    params.setAbsoluteErrorTol(1e-9)
    params.setlambdaUpperBound(LM_LAMBDA_UPPER)
    t0 = time.perf_counter()

    def hook(it, before, after):
        print(f"[{label}] iteration {it:2d}: cost {before:.6g} -> {after:.6g}  ({time.perf_counter() - t0:.1f} s)",
              file=sys.stderr, flush=True)

    if progress:
        params.iterationHook = hook
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = opt.optimize()
    return result, opt.iterations(), graph.error(values), graph.error(result)


def robust_weights(observations, residuals, sqrt_infos, conf, whitened=None):
    """IRLS weights: Huber on each match's Mahalanobis distance, 0 beyond the 99.9 % chi2(3) cut.

    The residual scale is estimated robustly (median) over all matches, so the cut
    adapts when the nominal noise model is off. ``whitened``: each pair's ``W e`` if the caller
    has it already (the live engine keeps it per pair and point).
    """
    r2 = [np.einsum("nij,nj->ni", W, e) for W, e in zip(sqrt_infos, residuals)] if whitened is None else whitened
    r2 = [np.sum(x * x, axis=1) for x in r2]
    sigma2 = np.median(np.concatenate(r2)) / CHI2_3_MEDIAN
    out = []
    for x, c in zip(r2, conf):
        u2 = x / sigma2
        w = np.minimum(1.0, HUBER_K / np.sqrt(np.maximum(u2, 1e-12)))
        out.append(np.where(u2 > OUTLIER_CUT_CHI2, 0.0, w * c))
    return out


MIN_ROBOT_POSES = 3


def solve(ds: Dataset, preds: Predictions, opt: SolveOptions) -> Solution:
    frames = {split_view_id(v)[1] for v in preds.views}
    if len(frames) < MIN_ROBOT_POSES:
        raise SolveError(f"{ds.root}: only {len(frames)} robot pose(s) with predictions; hand-eye calibration "
                         f"needs at least {MIN_ROBOT_POSES}, with rotations about two different axes")
    check_motion(ds.base_T_ee, frames, str(ds.root / ds.meta["robot"]["poses"]))  # before any initialisation
    timings = {}
    t = time.perf_counter()
    observations = build_observations(preds, opt.max_matches_per_pair, seed=opt.seed)
    if not observations:
        raise SolveError(f"predictions '{preds.name}': no view pair has enough valid matches")
    timings["observations"] = time.perf_counter() - t

    t = time.perf_counter()
    visual_poses = None
    if opt.init == "colmap":
        from calib3r_graph.io.predictions import read_poses_csv

        visual_poses = read_poses_csv(ds.root / "predictions" / preds.name / "poses.csv")
    init = initialise(sorted(preds.views), observations, ds.base_T_ee, str(ds.root / ds.meta["robot"]["poses"]),
                      visual_poses, seed=opt.seed)
    timings["initialisation"] = time.perf_counter() - t
    used = set(init.base_T_cam)
    pairs = [(o, m) for o, m in zip(observations, init.inliers) if o.view_a in used and o.view_b in used]
    observations = [o for o, _ in pairs]
    inliers = [m if m is not None else np.zeros(len(o), bool) for o, m in pairs]
    views = sorted(used)
    cameras = [c for c in ds.cameras if any(split_view_id(v)[0] == c for v in views)]
    keys = Keys(views, cameras)
    Ks = {v: preds.views[v].K for v in views}
    values = initial_values(keys, init, opt.noise.depth_correction_sigma > 0)
    conf = [o.weight for o in observations]
    weights = [c * m for c, m in zip(conf, inliers)]

    t = time.perf_counter()
    history = []

    def build_graph(scene_weights, noise):
        graph = gtsam.NonlinearFactorGraph()
        add_scene_factors(graph, keys, observations, scene_weights, values, Ks, noise, opt.reprojection)
        add_robot_factors(graph, keys, views, ds.base_T_ee, {c: values.atPose3(keys.hand_eye(c)) for c in cameras},
                          noise)
        add_scale_gauge_factors(graph, keys, views, noise)
        add_depth_correction_priors(graph, keys, views, noise)
        return graph

    def nominal_whitening():
        return [point_sqrt_info(o, Ks[o.view_a], Ks[o.view_b],
                                values.atPose3(keys.pose(o.view_a)).between(values.atPose3(keys.pose(o.view_b))),
                                values.atDouble(keys.scale(o.view_b)) / values.atDouble(keys.scale(o.view_a)),
                                opt.noise, np.ones(len(o))) for o in observations]

    n_rounds = opt.irls_rounds + 1 + int(opt.noise_calibration)
    weak = []  # views whose scene factors the rounds leave too weak to determine them
    sigma0_sq, kappa, robot_factor, robot_fit = 1.0, 1.0, 1.0, None
    noise = opt.noise
    for rnd in range(n_rounds):
        label = f"LM round {rnd + 1}/{n_rounds}"
        if opt.noise_calibration and rnd == n_rounds - 1:
            # Final round: scene information scaled by 1 / (sigma0^2 kappa), measured at the robust solution.
            residuals = match_residuals(observations, values, keys)
            grid = {v: preds.views[v].depth.shape[::-1] for v in views}
            sigma0_sq, kappa = noise_calibration(observations, residuals, nominal_whitening(), weights, grid)
            log.info("scene noise calibration: variance factor %.3g, design effect %.1f (matches per independent "
                     "observation)", sigma0_sq, kappa)
            weights = [w / (sigma0_sq * kappa) for w in weights]
            # Robot factor group: chi2 over its redundancy (6 per frame, less ee_T_cam and the
            # world's similarity). Real arms are often worse than their spec; never better.
            chi2, n_frames = robot_chi2(keys, views, ds.base_T_ee, values, opt.noise)
            robot_factor = max(1.0, chi2 / max(6 * n_frames - 13, 1))
            robot_fit = (float(chi2), 6 * n_frames - 13)  # under the nominal robot noise
            if not np.isfinite(robot_factor):  # a zero robot sigma: the marginals below report it
                robot_factor = 1.0
            if robot_factor > 1.0:
                log.warning("the robot poses and the images disagree %.1fx more than --robot-sigma-mm/-deg allow "
                            "(%.2g mm, %.2g deg): either the arm is that much noisier, or a view's geometry is "
                            "wrong; using %.2g mm, %.2g deg", np.sqrt(robot_factor), opt.noise.robot_sigma_mm,
                            opt.noise.robot_sigma_deg, opt.noise.robot_sigma_mm * np.sqrt(robot_factor),
                            opt.noise.robot_sigma_deg * np.sqrt(robot_factor))
            noise = dataclasses.replace(opt.noise, robot_sigma_mm=opt.noise.robot_sigma_mm * np.sqrt(robot_factor),
                                        robot_sigma_deg=opt.noise.robot_sigma_deg * np.sqrt(robot_factor))
            label += " (noise-calibrated)"
        for v, reason in unsupported_views(views, observations, weights).items():
            log.warning("%s: %s; solved without it", view_words(v), reason)
            weak.append({"view": v, "reason": reason})
        if weak and {d["view"] for d in weak} & set(views):
            gone = {d["view"] for d in weak}
            views, cameras, observations, conf, weights, inliers = without_views(
                gone, keys, values, views, cameras, observations, conf, weights, inliers)
        graph = build_graph(weights, noise)
        with gtsam_keys_named(keys):
            values, iters, e0, e1 = levenberg_marquardt(graph, values, opt.max_iterations, label, opt.progress)
        history.append({"round": rnd + 1, "iterations": iters, "initial_error": e0, "final_error": e1,
                        "matches_used": int(sum((w > 0).sum() for w in weights))})
        if rnd < opt.irls_rounds:
            weights = robust_weights(observations, match_residuals(observations, values, keys),
                                        nominal_whitening(), conf)
    timings["optimisation"] = time.perf_counter() - t

    t = time.perf_counter()
    try:  # any of these can find the system indeterminate (gtsam) or singular (the field's Hessian)
        marginals = gtsam.Marginals(graph, values)
        covariance_model = {c: marginals.marginalCovariance(keys.hand_eye(c)) for c in cameras}
        scale_variance = {c: float(marginals.marginalCovariance(keys.metric(c))[0, 0]) for c in cameras}
    except RuntimeError as e:
        from calib3r_graph.errors import library_error

        cause = (library_error(e, keys.describe) or (next(iter(str(e).strip().splitlines()), ""), 0))[0]
        raise SolveError(f"the calibration is not observable from this data ({cause})"
                         + _unobservable_because(ds, preds, views)) from None
    # The systematic part: a kinematic error field measured from the robot residuals (systematic.py).
    robot = [(keys.hand_eye(split_view_id(v)[0]), keys.pose(v), ds.base_T_ee[split_view_id(v)[1]])
             for v in robot_views(keys, views)]
    with gtsam_keys_named(keys):
        systematic = systematic_errors(graph, values, robot, {c: (keys.hand_eye(c), keys.metric(c)) for c in cameras})
    covariance = {c: covariance_model[c] + systematic[c].covariance for c in cameras}
    metric = {}
    for c in cameras:
        lam = values.atDouble(keys.metric(c))
        sigma_model = float(np.sqrt(scale_variance[c]))
        metric[c] = (lam, float(np.hypot(sigma_model, lam * systematic[c].scale_sigma_rel)))
    timings["covariance"] = time.perf_counter() - t
    used_frames = {split_view_id(v)[1] for v in views}
    diagnostics = motion_diagnostics(ds.base_T_ee, used_frames) + pose_disagreements_kept(preds)
    gain, gain_axis = systematic_error_gain(ds.base_T_ee, used_frames)
    residuals = np.concatenate([np.linalg.norm(e, axis=1) for e in match_residuals(observations, values, keys)])
    stats_out = {"rounds": history, "timings_s": timings,
                 "noise_calibration": {"variance_factor": sigma0_sq, "design_effect": kappa,
                                       "robot_variance_factor": robot_factor,
                                       "robot_chi2_dof": robot_fit,
                                       "robot_sigma_used": [noise.robot_sigma_mm, noise.robot_sigma_deg],
                                       "method": "scene information scaled by 1/(variance factor x design effect)"
                                       if opt.noise_calibration else "off"},
                 "views_used": len(views), "pairs_used": len(observations),
                 "matches_used": history[-1]["matches_used"],
                 "matches_total": int(sum(len(o) for o in observations)),
                 "match_residual_median_rel": float(np.median(residuals)),
                 # mm of ee_T_cam translation per mm of systematic relative-translation error (uncertainty.py)
                 "systematic_error_gain": {"mm_per_mm": gain, "ee_direction": gain_axis.tolist()},
                 "systematic": {c: systematic[c].to_json() for c in cameras}}
    sol = Solution(
        ee_T_cam={c: values.atPose3(keys.hand_eye(c)) for c in cameras},
        covariance=covariance, covariance_model=covariance_model, systematic=systematic, metric_scale=metric,
        base_T_cam={v: values.atPose3(keys.pose(v)) for v in views},
        depth_scale={v: values.atDouble(keys.scale(v)) for v in views},
        depth_correction={v: depth_correction(values, keys, v) for v in views},
        init_ee_T_cam=init.ee_T_cam, stats=stats_out,
        views_dropped=dropped_by_frontend(preds) + init.dropped_views + weak, diagnostics=diagnostics,
        graph=graph, values=values, keys=keys, observations=observations,
        scene_weight_scale=1.0 / (sigma0_sq * kappa))
    if wanted(opt.jackknife, len(used_frames)):
        t = time.perf_counter()
        with gtsam_keys_named(keys):
            _cover_with_jackknife(ds, preds, opt, sol)
        timings["jackknife"] = time.perf_counter() - t
    for c in cameras:
        diagnostics += covariance_diagnostics(c, sol.ee_T_cam[c], sol.covariance[c])
    for msg in diagnostics:
        log.warning("%s", msg)
    add_camera_model(sol, ds, weights, Ks, noise)  # the intrinsics' own sigma, after the motion's diagnostics
    return sol


def _unobservable_because(ds, preds, views) -> str:
    """What the used views' motion lacks, in words, and the views the frontend could not use (the
    rest may rotate about one axis only although the recording did not)."""
    frames = {split_view_id(v)[1] for v in views}
    motion = [m for m in motion_diagnostics(ds.base_T_ee, frames) if "axes" in m or "rotates less" in m]
    dropped = list(preds.info.get("unusable_views", [])) + [v for v in preds.views if v not in views]
    out = "".join(f"; {m}" for m in motion)
    if dropped:
        out += f"; the frontend could not use {', '.join(sorted(set(dropped)))}"
    return out


def _cover_with_jackknife(ds, preds, opt, sol):
    """Leave-one-pose-out solves; each camera's total covariance becomes the cover of the modelled
    one and the jackknife's (jackknife.cover), and solver.jackknife records both;
    solver.influential_pose names a pose the rest of the data reject (or is None)."""
    jk, suspect = jackknife(ds, preds, opt, sol, solve, progress=opt.progress)
    sol.stats["influential_pose"] = suspect
    if suspect:
        sol.diagnostics.append(influential_pose_message(suspect))
    for c, rep in jk.items():
        before = np.asarray(sol.covariance[c])
        sol.covariance[c] = cover(before, np.asarray(rep["covariance"]))
        rep["covariance_before"] = before.tolist()
    sol.stats["jackknife"] = jk


def influential_pose_message(suspect: dict) -> str:
    """The diagnostic for jackknife.influential_pose's result, with the measured chi2 ratio (to two
    decimals: 1.59 is not "2x")."""
    return (f"robot pose {suspect['frame']}: without it the robot and the images agree {suspect['chi2_ratio']:.2f}x "
            f"better (robot chi2 per dof {suspect['chi2_per_dof']:.3g} -> {suspect['chi2_per_dof_without']:.3g}, "
            f"F = {suspect['F']:.3g}, p = {suspect['p']:.2g}): check its image and its pose (a wrong pair "
            "geometry or a wrong robot pose)")


@contextlib.contextmanager
def gtsam_keys_named(keys):
    """GTSAM's indeterminate-system error inside becomes a SolveError that names the view (camera,
    frame) or the camera behind the key, never the key itself (s6, x18)."""
    from calib3r_graph.errors import library_error

    try:
        yield
    except RuntimeError as e:
        described = library_error(e, keys.describe)
        if described is None or described[1] != SolveError.exit_code:
            raise
        raise SolveError(f"the calibration is not observable from this data ({described[0]})") from e
