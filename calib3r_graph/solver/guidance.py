"""Live guidance: the next flange poses to record, generated from the current solution and scored by
the expected reduction of the **total** sigma (noise model, systematic part and few-pose jackknife
cover), with the stop rule's objective (:func:`objective`). ``live/session.py`` calls
:func:`candidate_poses` and :func:`score_candidates` after each update; the offline ranking of a
candidates file (``calib3r-graph plan``) and the candidate factors both share are in ``plan.py``.
How the guide was measured is in docs/live.md and docs/live-notes.md.
"""

from dataclasses import dataclass

import gtsam
import numpy as np

from calib3r_graph.io.predictions import split_view_id
from calib3r_graph.solver.plan import (StackedPoints, candidate_factors, distinct_points, matched_view_angle_deg,
                                        scene_points, scene_points_by_view, view_axes)

# Candidate motions: rotations about an axis through the scene's centroid (the camera keeps looking
# at it from the same distance), 20 and 35 degrees: the range that moves ee_T_cam's translation
# (uncertainty.systematic_error_gain asks for 20-40 degrees).
ROTATION_STEPS_DEG = (20.0, 35.0)
# A new distance must differ from the current one by 10 % or more to measure the scale.
MIN_DISTANCE_CHANGE = 0.10
# Toward / away distances for the metric scale, as fractions of the median distance seen so far:
# one move of Delta measures the scale to about sigma_robot / Delta (0.2 mm over 20 % of 0.4 m:
# 0.25 %), so they are tried even where every view so far was at one distance (an orbit, like
# rwhe_kuka_2's): the distances seen so far are grown by DISTANCE_MARGIN of their median (see
# distance_band). Anchored to the median, not to each view's distance, so that guided views do not
# creep closer and closer: 20 % changes the image scale by 1.25x at most, which the frontends match
# (measured on the simulated orbit, bench/live_scale.py: a view 30 % closer, at 0.7x the median
# depth, found no verified pair).
DISTANCE_STEPS = (0.10, 0.20)
DISTANCE_MARGIN = max(DISTANCE_STEPS)
ORIENTATION_MARGIN_DEG = 15.0  # the visited orientations, grown by this, bound the candidates'


@dataclass
class Proposal:
    base_T_ee: gtsam.Pose3
    kind: str  # "toward", "away" (fixed orientation, along the line to the scene), "rotate", "look-at", "recorded"
    objective_after: float  # the stop rule's quantity after it (largest total sigma / target, combined)
    gain: float  # expected reduction of that objective
    sigma_after: dict  # camera -> sigma_ee_frame (total)
    visible_points: int
    frame: str | None = None  # a recorded frame (guided replay)


def scene_geometry(sol) -> tuple[np.ndarray, np.ndarray]:
    """(centroid in the base frame (median of the solved scene points), the reference camera's
    distances to it (m) over its views)."""
    ref = list(sol.ee_T_cam)[0]
    pts, centres = [], []
    for v, T in sol.base_T_cam.items():
        if split_view_id(v)[0] != ref:
            continue
        P = scene_points(sol, v)
        if len(P):
            pts.append(P @ T.rotation().matrix().T + T.translation())
        centres.append(T.translation())
    centroid = np.median(np.concatenate(pts), axis=0)
    return centroid, np.linalg.norm(np.array(centres) - centroid, axis=1)


def objective(covs: dict, ee_T_cam: dict, scale_rel: dict, distance_m: float, target_mm: float,
              target_deg: float) -> float:
    """sum over cameras of |sigma / target| over the six ee axes and the metric scale (as the mm it
    moves a point at the median scene distance): 1 or less on every axis is the stop rule's "done"."""
    from calib3r_graph.io.results import covariance_in_ee_frame

    out = 0.0
    for c, C in covs.items():
        s = np.sqrt(np.maximum(np.diag(covariance_in_ee_frame(ee_T_cam[c], C)), 0))
        z = np.r_[np.degrees(s[:3]) / target_deg, s[3:] * 1e3 / target_mm, scale_rel[c] * distance_m * 1e3 / target_mm]
        out += float(np.sqrt(np.sum(z * z)))
    return out


def distance_band(dist) -> tuple[float, float]:
    """(nearest, farthest) camera-to-centroid distance (m) a proposal may have: the distances seen
    so far (``dist``), grown by DISTANCE_MARGIN of their median."""
    d_med = float(np.median(dist))
    return (min(float(np.min(dist)), d_med * (1 - DISTANCE_MARGIN)),
            max(float(np.max(dist)), d_med * (1 + DISTANCE_MARGIN)))


def _look_from(T: gtsam.Pose3, centroid, axis, angle) -> gtsam.Pose3:
    """Camera pose T rotated by ``angle`` about ``axis`` (base frame) through ``centroid``."""
    R = gtsam.Rot3.AxisAngle(gtsam.Unit3(np.asarray(axis, float)).point3(), angle)
    t = R.matrix() @ (T.translation() - centroid) + centroid
    return gtsam.Pose3(R.compose(T.rotation()), t)


def candidate_poses(sol, base_T_ee: dict, margin_m=0.05, box=None, rng=None, n_random=16) -> list:
    """[(kind, base_T_ee)] inside the visited region (flange positions grown by ``margin_m``, or
    ``box`` = (lo, hi) in the base frame, m; orientations within the visited ones + 15 degrees),
    the camera looking at the scene's centroid from the distances seen so far (grown as
    :func:`distance_band` says, so that a move toward or away can measure the scale)."""
    rng = rng or np.random.default_rng(0)
    ref = list(sol.ee_T_cam)[0]
    X = sol.ee_T_cam[ref]
    centroid, dist = scene_geometry(sol)
    d_lo, d_hi, d_med = float(dist.min()), float(dist.max()), float(np.median(dist))
    sign_ok = lambda kind, target, d: (target < d) == (kind == "toward")  # noqa: E731
    frames = sorted(base_T_ee)
    p = np.array([base_T_ee[f].translation() for f in frames])
    lo, hi = (p.min(0) - margin_m, p.max(0) + margin_m) if box is None else (np.asarray(box[0]), np.asarray(box[1]))
    from calib3r_graph.solver.systematic import configuration

    _, w = configuration([base_T_ee[f] for f in frames])
    R_mean = base_T_ee[frames[0]].rotation().compose(
        gtsam.Rot3.Expmap(np.mean([gtsam.Rot3.Logmap(base_T_ee[frames[0]].rotation().between(base_T_ee[f].rotation()))
                                   for f in frames], axis=0)))
    max_angle = np.linalg.norm(w, axis=1).max() + np.radians(ORIENTATION_MARGIN_DEG)
    views = [v for v in sol.base_T_cam if split_view_id(v)[0] == ref]
    out = []
    # weakest directions of the current total covariance, in the ee frame
    from calib3r_graph.io.results import covariance_in_ee_frame

    C = covariance_in_ee_frame(X, np.asarray(sol.covariance[ref]))
    rot_weak = np.linalg.eigh(C[:3, :3])[1][:, -1]
    t_weak = np.linalg.eigh(C[3:, 3:])[1][:, -1]
    perp = np.linalg.svd(t_weak[None])[2][1:]  # two axes perpendicular to the weak translation
    for v in views:
        T = sol.base_T_cam[v]
        c = T.translation()
        d = np.linalg.norm(c - centroid)
        targets = [("toward", d_lo), ("away", d_hi)] + [(kind, d_med * (1 + sign * f)) for f in DISTANCE_STEPS
                                                         for kind, sign in (("toward", -1), ("away", 1))]
        for kind, target in targets:
            if sign_ok(kind, target, d) and abs(target - d) >= MIN_DISTANCE_CHANGE * d - 1e-9:
                out.append((kind, gtsam.Pose3(T.rotation(), centroid + (c - centroid) * target / d)))
        R_ee = T.compose(X.inverse()).rotation().matrix()
        for axis in [rot_weak, *perp]:
            for deg in ROTATION_STEPS_DEG:
                for sign in (1, -1):
                    out.append(("rotate", _look_from(T, centroid, R_ee @ axis, sign * np.radians(deg))))
    for _ in range(n_random):
        T = sol.base_T_cam[views[rng.integers(len(views))]]
        T = _look_from(T, centroid, rng.normal(size=3), np.radians(rng.uniform(10, 35)))
        r = rng.uniform(*distance_band(dist))  # a rotation and a change of distance at once
        out.append(("look-at", gtsam.Pose3(T.rotation(), centroid + (T.translation() - centroid) * r
                                           / np.linalg.norm(T.translation() - centroid))))
    keep = []
    for kind, C_cam in out:
        E = C_cam.compose(X.inverse())
        inside = np.all(E.translation() >= lo) and np.all(E.translation() <= hi)
        if inside and np.linalg.norm(gtsam.Rot3.Logmap(R_mean.between(E.rotation()))) <= max_angle:
            keep.append((kind, E))
    return _within_budget(keep, rng)


# Candidates scored per update. Scoring costs about 17 ms a candidate (2000 scene points; 193 candidates
# took 3.2 s at 16 frames) and the candidates grow with the views (15 per view), so at 30 frames the
# guidance alone took 6-11 s on a loaded 2-core machine; 48, drawn evenly over the kinds, keep it under
# a second and every kind (toward, away, rotate, look-at) in the running.
MAX_CANDIDATES = 48


def _within_budget(cands: list, rng) -> list:
    """At most MAX_CANDIDATES of ``cands``: round-robin over the kinds, each kind in a random order."""
    if len(cands) <= MAX_CANDIDATES:
        return cands
    by_kind = {}
    for c in cands:
        by_kind.setdefault(c[0], []).append(c)
    queues = [[group[i] for i in rng.permutation(len(group))] for group in by_kind.values()]
    out = []
    while len(out) < MAX_CANDIDATES:
        for q in queues:
            if q and len(out) < MAX_CANDIDATES:
                out.append(q.pop())
    return out


def score_candidates(sol, preds, noise, base_T_ee: dict, candidates: list, target_mm: float, target_deg: float,
                     information=None, seed=0) -> list:
    """[Proposal] for candidates [(kind, base_T_ee, frame or None)], best first: the expected
    objective (:func:`objective`) of the TOTAL covariance after each, the metric scale included.

    * Noise model: the candidate's factors (:func:`candidate_factors`) added to the information
      matrix ``H`` of the current graph: their new variables eliminated (Schur complement), the
      rank-13 update ``D`` on (ee_T_cam, the overlapping view's pose and scale) gives the marginals
      by Woodbury, ``S' = S - S_:U D (I + S_UU D)^-1 S_U:``, with ``S = H^-1`` (no re-solve).
    * Systematic part, first pass: it scales with the squared systematic-error gain of the motion
      (``uncertainty.systematic_error_gain``: mm of ee_T_cam per mm of systematic error, from the
      rotational diversity), so the candidate's effect on the gain rescales it. That gain knows
      nothing of the scale: on an orbit the field's share of the scale (systematic.py: a field
      gradient along the viewing axis looks exactly like a scale change) falls only with a move
      toward or away from the scene. So the ``SHORTLIST`` best, and the best of each kind, are
      scored again with the field propagated exactly through the graph with the candidate's factors
      (``systematic.propagate`` on ``H + the candidate's information``, the measured tau).
    * The few-pose cover (jackknife): a leave-one-out spread shrinks as 1/n with one more pose.
    ``information``: (H^-1, offsets[, H]) of ``sol.graph`` at ``sol.values`` (computed when None; H,
    where given, saves the exact re-scoring an inversion of H^-1: 17 ms a pass on tabb_ds1 at 60 frames).
    """
    from calib3r_graph.solver.systematic import linear_system
    from calib3r_graph.solver.uncertainty import systematic_error_gain

    keys, cameras = sol.keys, list(sol.ee_T_cam)
    if information is None:
        H, offsets, _ = linear_system(sol.graph, sol.values)
        information = (np.linalg.inv(H), offsets, H)
    S, offsets = information[:2]
    H = information[2] if len(information) > 2 else None
    out_keys = [k for c in cameras for k in (keys.hand_eye(c), keys.metric(c))]
    out_idx = np.concatenate([np.arange(offsets[k][0], offsets[k][0] + offsets[k][1]) for k in out_keys])
    _, dist = scene_geometry(sol)
    d_med = float(np.median(dist))
    # the poses the solution uses: a frame whose views the solve left out adds no motion (the systematic
    # gain) and no leave-one-out sample, and the next solve's jackknife counts the poses it uses
    frames = [f for f in sol.frames if f in base_T_ee]
    gain_before = systematic_error_gain(base_T_ee, frames)[0]
    rng = np.random.default_rng(seed)
    k_new = (gtsam.symbol("n", 0), gtsam.symbol("m", 0))
    points = scene_points_by_view(sol)
    stacked = StackedPoints.of(sol, preds, distinct_points(points))
    axes = view_axes(sol)
    max_angle = matched_view_angle_deg(sol, axes)
    proposals, parts = [], []
    loo = _leave_one_out(sol, len(frames))
    for kind, E, frame in candidates:
        fs, vals, best, n_vis = candidate_factors(sol, preds, noise, E, rng, keys_new=k_new, points=points,
                                                  max_angle_deg=max_angle, axes=axes, stacked=stacked)
        S_out = S[np.ix_(out_idx, out_idx)]
        D, U = None, None
        if best is not None:
            D, U = _candidate_reduced(sol, fs, vals, offsets, k_new)
            S_uu, S_ou = S[np.ix_(U, U)], S[np.ix_(out_idx, U)]
            S_out = S_out - S_ou @ D @ np.linalg.solve(np.eye(len(U)) + S_uu @ D, S_ou.T)
        # A view that overlaps no solved view (a --candidates pose looking elsewhere) adds nothing the
        # solve could use: neither its motion's rotations (the systematic gain) nor a jackknife sample.
        if best is None:
            factor = 1.0
            jk_after = {c: np.asarray(r["covariance"]) for c, r in sol.stats.get("jackknife", {}).items()}
        else:
            gain_after = systematic_error_gain({**base_T_ee, "_candidate": E}, frames + ["_candidate"])[0]
            factor = (gain_after / gain_before) ** 2 if np.isfinite(gain_before) and gain_before > 0 else 1.0
            jk_after = _jackknife_after(sol, loo, D, U, len(frames))
        sys_after = {c: (sol.systematic[c].covariance * factor, sol.systematic[c].scale_sigma_rel * np.sqrt(factor))
                     for c in cameras if c in sol.systematic}
        J, sig = _objective_after(sol, S_out, sys_after, jk_after, d_med, target_mm, target_deg)
        proposals.append(Proposal(E, kind, J, 0.0, sig, n_vis, frame))
        parts.append((fs, vals, S_out, jk_after))
    _rescore_systematic(sol, base_T_ee, proposals, parts, offsets, S, k_new, d_med, target_mm, target_deg, H)
    J_now = objective(sol.covariance, sol.ee_T_cam, {c: sol.metric_scale[c][1] / abs(sol.metric_scale[c][0])
                                                     for c in cameras}, d_med, target_mm, target_deg)
    for p in proposals:
        p.gain = J_now - p.objective_after
    return sorted(proposals, key=lambda p: p.objective_after)


SHORTLIST = 4  # candidates re-scored with the exact systematic part (besides the best of each kind)


def _candidate_reduced(sol, fs, vals, offsets, k_new):
    """(D, U): the candidate factors' information on the current variables they touch, its own new
    variables eliminated (Schur complement), and those variables' columns ``U`` in ``offsets``."""
    M, order, dims = _candidate_information(sol, fs, vals, offsets, k_new)
    old = [k for k in order if k in offsets]
    m = sum(dims[k] for k in old)
    A, B, Cn = M[:m, :m], M[:m, m:], M[m:, m:]
    D = A - B @ np.linalg.solve(Cn + 1e-12 * np.eye(len(Cn)), B.T)
    return D, np.concatenate([np.arange(offsets[k][0], offsets[k][0] + offsets[k][1]) for k in old])


def _candidate_information(sol, fs, vals, offsets, k_new):
    """(M, key order, dims): the candidate factors' information, linearised at the current values
    (new variables at their predicted values), old keys first in ``offsets``' order, then the new."""
    g = gtsam.NonlinearFactorGraph()
    for f in fs:
        g.add(f)
    gkeys = sorted(g.keyVector())  # a list: iterating gtsam's KeySet temporary is not safe
    for k in gkeys:
        if not vals.exists(k):
            _insert_like(vals, sol.values, k)
    lin = g.linearize(vals)
    old = [k for k in gkeys if k in offsets]
    new = [k for k in gkeys if k not in offsets]
    dims = {k: (offsets[k][1] if k in offsets else (6 if k == k_new[0] else 1)) for k in gkeys}
    order = old + new
    pos, col = {}, 0
    for k in order:
        pos[k] = (col, dims[k])
        col += dims[k]
    M = np.zeros((col, col))
    for i in range(lin.size()):
        f = lin.at(i)
        idx = np.concatenate([np.arange(pos[k][0], pos[k][0] + pos[k][1]) for k in f.keys()])
        M[np.ix_(idx, idx)] += f.augmentedInformation()[:len(idx), :len(idx)]
    return M, order, dims


def _leave_one_out(sol, n: int):
    """({frame: (kept columns, Cholesky factor of H_-i, dx_-i)}, offsets) of the linearised
    jackknife (``jackknife.linearised_leave_one_out``) about ``sol``, for :func:`_jackknife_after`;
    None where the update after one more pose will have no jackknife (``JACKKNIFE_BELOW``)."""
    from calib3r_graph.solver.jackknife import (JACKKNIFE_BELOW, at_linear_minimum, factor_system,
                                                linearised_leave_one_out)

    if not sol.stats.get("jackknife") or n + 1 >= JACKKNIFE_BELOW:
        return None
    system, systems = at_linear_minimum(factor_system(sol.graph, sol.values)), {}
    linearised_leave_one_out(sol.graph, sol.values, sol.keys, list(sol.base_T_cam), system, systems)
    return systems, system[1]


def _jackknife_after(sol, loo, D, U, n: int) -> dict:
    """{camera: 6x6} the linearised jackknife's covariance of ee_T_cam once the candidate is added.

    Below ``JACKKNIFE_BELOW`` poses the few-pose cover usually dominates the total (rwhe_kuka_1 at
    5-12 poses: 3.6-50 mm of it against 1-4 mm of the noise model), and it is the spread of the
    leave-one-pose-out estimates: it falls with a candidate that makes the estimate depend less on
    any one pose, not as 1/n. With the candidate's information ``D`` on the columns ``U`` (its
    factors, its own variables eliminated), the sample without pose i moves from
    ``dx_-i = -H_-i^-1 g_i`` to ``-(H_-i + D)^-1 g_i``: at the current solution the candidate's
    expected residual, hence its gradient, is zero. By Woodbury, with ``Z = H_-i^-1 E_U``:
    ``dx_-i - Z (I + D Z_U)^-1 D dx_-i[U]``. A sample whose pose takes away the view the candidate
    overlaps keeps its dx (the candidate's robot factor alone does not reach ee_T_cam), and leaving
    the candidate itself out gives the current estimate, a zero sample. Without ``loo``: the
    current cover shrunk as n / (n + 1) where the next update has a jackknife, else none."""
    from calib3r_graph.solver.jackknife import JACKKNIFE_BELOW

    jk = sol.stats.get("jackknife", {})
    if loo is None:
        if n + 1 >= JACKKNIFE_BELOW:
            return {}
        return {c: np.asarray(r["covariance"]) * n / (n + 1) for c, r in jk.items()}
    out = {}
    for c, by_frame in jackknife_samples_after(sol, loo, D, U).items():
        if c in jk and len(by_frame) >= 2:  # with the zero sample, 3 or more (as jackknife._jackknife_report)
            xs = np.array([np.zeros(6), *by_frame.values()])
            out[c] = (len(xs) - 1) / len(xs) * (xs - xs.mean(0)).T @ (xs - xs.mean(0))
    return out


def jackknife_samples_after(sol, loo, D=None, U=None) -> dict:
    """{camera: {frame: dx of ee_T_cam (6,)}}: each linearised leave-one-pose-out sample once the
    candidate's information ``D`` on the columns ``U`` is added (:func:`_jackknife_after`)."""
    from scipy.linalg import cho_solve

    systems, offsets = loo
    he = {c: offsets[sol.keys.hand_eye(c)][0] for c in sol.ee_T_cam}
    out = {c: {} for c in he}
    for frame, (keep, cho, dx) in systems.items():
        if D is not None:
            pos = np.minimum(np.searchsorted(keep, U), len(keep) - 1)
            if np.array_equal(keep[pos], U):
                E = np.zeros((len(keep), len(U)))
                E[pos, np.arange(len(U))] = 1.0
                Z = cho_solve(cho, E, check_finite=False)
                dx = dx - Z @ np.linalg.solve(np.eye(len(U)) + D @ Z[pos], D @ dx[pos])
        for c, a in he.items():
            i = int(np.searchsorted(keep, a))
            out[c][frame] = dx[i:i + 6]
    return out


def _objective_after(sol, S_out, sys_after: dict, jk_after: dict, d_med, target_mm, target_deg):
    """(objective, {camera: sigma_ee_frame}) of the total after a candidate: the noise model's
    (ee_T_cam, scale) marginal ``S_out`` (7 per camera), ``sys_after`` {camera: (6x6, scale rel)}
    and the jackknife's cover ``jk_after`` {camera: 6x6} (:func:`_jackknife_after`)."""
    from calib3r_graph.io.results import covariance_in_ee_frame, sigma_ee_frame
    from calib3r_graph.solver.jackknife import cover

    covs, scale_rel, sig = {}, {}, {}
    for i, c in enumerate(sol.ee_T_cam):
        model, var_l = S_out[7 * i:7 * i + 6, 7 * i:7 * i + 6], S_out[7 * i + 6, 7 * i + 6]
        sys_cov, sys_rel = sys_after.get(c, (np.zeros((6, 6)), 0.0))
        total = model + sys_cov
        if c in jk_after:
            total = cover(total, jk_after[c])
        covs[c] = total
        scale_rel[c] = float(np.hypot(np.sqrt(max(var_l, 0)) / abs(sol.metric_scale[c][0]), sys_rel))
        sig[c] = sigma_ee_frame(np.sqrt(np.maximum(np.diag(covariance_in_ee_frame(sol.ee_T_cam[c], total)), 0)))
    return objective(covs, sol.ee_T_cam, scale_rel, d_med, target_mm, target_deg), sig


def _rescore_systematic(sol, base_T_ee, proposals, parts, offsets, S, k_new, d_med, target_mm, target_deg, H=None):
    """Re-score the shortlist (see :func:`score_candidates`) in place with the systematic field
    propagated through the graph extended by each candidate's factors. ``H``: the information matrix
    whose inverse is ``S`` (inverted from ``S`` when None)."""
    from calib3r_graph.solver.graph import robot_views
    from calib3r_graph.solver.systematic import key_offsets, propagate

    cameras = list(sol.ee_T_cam)
    tau = next((sol.systematic[c].tau for c in cameras if c in sol.systematic), None)
    if tau is None or not np.asarray(tau).sum() > 0:
        return  # no field measured: nothing systematic to re-score
    keys = sol.keys
    order = sorted(range(len(proposals)), key=lambda i: proposals[i].objective_after)
    pick = set(order[:SHORTLIST])
    for kind in {p.kind for p in proposals}:
        pick.add(next(i for i in order if proposals[i].kind == kind))
    robot = [(keys.hand_eye(split_view_id(v)[0]), keys.pose(v), base_T_ee[split_view_id(v)[1]])
             for v in robot_views(keys, list(sol.base_T_cam))]
    out_keys = [k for c in cameras for k in (keys.hand_eye(c), keys.metric(c))]
    # the robot factors are all propagate needs (a live update keeps them apart: its whole graph is
    # built only where asked), on the same keys as the whole graph's
    base = getattr(sol, "robot_graph", None)
    base = sol.graph if base is None else base
    for i in pick:
        fs, vals, S_out, jk_after = parts[i]
        graph = gtsam.NonlinearFactorGraph(base)
        values = gtsam.Values(sol.values)
        for f in fs:
            graph.add(f)
        M, korder, dims = _candidate_information(sol, fs, vals, offsets, k_new)
        for k in korder:
            if k not in offsets:  # the candidate's own variables (vals holds the old ones it touches too)
                _insert_like(values, vals, k)
        if H is None:
            H = np.linalg.inv(S)
        aug = key_offsets(graph, values)
        n_aug = sum(d for _, d in aug.values())
        perm = np.concatenate([np.arange(aug[k][0], aug[k][0] + aug[k][1]) for k in offsets])
        H_aug = np.zeros((n_aug, n_aug))
        H_aug[np.ix_(perm, perm)] = H
        idx = np.concatenate([np.arange(aug[k][0], aug[k][0] + dims[k]) for k in korder])
        H_aug[np.ix_(idx, idx)] += M
        E = proposals[i].base_T_ee
        try:
            blocks = propagate(graph, values, robot + [(keys.hand_eye(cameras[0]), k_new[0], E)], tau, out_keys,
                               system=(H_aug, aug))
        except np.linalg.LinAlgError:  # keep the first pass's score for this one
            continue
        sys_after = {}
        for c in cameras:
            lam = abs(values.atDouble(keys.metric(c)))
            sys_after[c] = (blocks[keys.hand_eye(c)], float(np.sqrt(max(blocks[keys.metric(c)][0, 0], 0)) / lam))
        J, sig = _objective_after(sol, S_out, sys_after, jk_after, d_med, target_mm, target_deg)
        proposals[i].objective_after, proposals[i].sigma_after = J, sig


def _insert_like(dst, src, k):
    for get in (src.atPose3, src.atDouble, src.atVector):
        try:
            dst.insert(k, get(k))
            return
        except RuntimeError:
            continue
    raise KeyError(k)
