"""Leave-one-robot-pose-out jackknife of ``ee_T_cam``: a covariance from the data's own spread.

With few robot poses the robot's kinematic error field cannot be measured (``systematic.py``
needs the residual of many poses), and the modelled covariance is over-confident: on
rwhe_kuka_1's 6-pose subsets only 70 % of the solutions were within 3 sigma of the full
recording's on every axis (95 % with the jackknife; bench/views_real.py). The jackknife needs no
model of that error: it leaves each pose out in turn, by a downdate of the solved graph's
information (:func:`linearised_jackknife`) or by re-solving (:func:`jackknife` with method
"resolve", solve's default: ``METHOD``; the n solves run in parallel processes,
:func:`leave_one_out_solves`). ``solve`` runs it by default below ``JACKKNIFE_BELOW`` poses and reports the
total covariance as the cover of both (``cover``); ``solve --jackknife always`` runs it at any size.

The same solves name a pose that the rest of the data reject (``influential_pose``: Baarda's
data snooping on the robot chi2); ``solve`` reports it in words and does not drop it.

The solver is passed in (``solve_fn``), so this module stays below ``solve``.
"""

import threading

import numpy as np

from calib3r_graph.io.predictions import split_view_id

# Below this many robot poses the jackknife runs by default. The field (systematic.py) has 18
# directions; its method-of-moments estimate has 3n - 7 residual dimensions, fewer than two per
# direction below 15 poses. Measured on rwhe_kuka_1 (bench/views_real.py): the share of 8-pose
# subsets within 3 sigma on every axis is 95 % with the measured field, 100 % with the jackknife.
JACKKNIFE_BELOW = 15
AXES = ("rx_deg", "ry_deg", "rz_deg", "x_mm", "y_mm", "z_mm")
# Baarda's significance for naming a pose that the rest of the data reject (influential_pose)
ALPHA = 0.001
MIN_POSES = 3  # solve.MIN_ROBOT_POSES: a leave-one-out with fewer left is no sample
# A linearised sample beyond 0.5 rad / 0.5 m is no sample: the first-order model's error grows as
# |dx|^2 / 2 (12 % at 0.5 rad), and such a step means the rest hardly determines ee_T_cam.
MAX_STEP = (0.5, 0.5)


# How solve's jackknife is computed (SolveOptions.jackknife_method, ``--jackknife-method``; None
# takes this): "resolve" (n re-solves, in parallel processes) or "linearised"
# (:func:`linearised_jackknife`; the live engine's). bench/jackknife.py (bench/results/jackknife.md,
# 2026-12-07): the covers of the total agree within 20 % on the sample, the simulator and
# rwhe_kuka_2, not on rwhe_kuka_1 (0.64 on a 10-pose subset, 0.79 on all 30 poses) nor on one of
# tabb_ds1's 10-frame windows (0.61). The gap is solve's robust re-weighting, which the linearised
# one holds: with it off (irls_rounds=0) the two agree within 7 % there. The re-solving cover repeats
# within 11 % across solve's seeds, so the gap is not its noise; both cover the full result equally
# often (rwhe_kuka_1's 6 / 8-pose subsets: 83 / 94 %, 56 / 78 % without a jackknife). solve keeps
# re-solving, the jackknife of the estimator it is; the linearised one costs 0.1-0.2 s instead of
# n solves (docs/uncertainty.md).
METHOD = "resolve"


def wanted(mode: str, poses: int) -> bool:
    """``mode``: "auto" (below JACKKNIFE_BELOW poses), "always" or "never"."""
    if mode not in ("auto", "always", "never"):
        raise ValueError(f"jackknife: '{mode}' is not auto, always or never")
    return mode == "always" or (mode == "auto" and poses < JACKKNIFE_BELOW)


def jackknife(ds, preds, opt, sol, solve_fn, progress=True) -> tuple[dict, dict | None]:
    """({camera: the jackknife covariance of ee_T_cam, its sigmas and their ratio to ``sol``'s},
    the pose the rest of the data reject or None (:func:`influential_pose`)).

    For each of the n frames the problem is solved without it (``solve_fn(ds, preds, opt)``,
    with the jackknife itself off); the spread of ee_T_cam over the solutions, in the tangent
    space at ``sol``'s, gives ``C = (n - 1)/n * sum (xi_i - mean)(xi_i - mean)^T`` (rad, m; the
    GTSAM Pose3 tangent order). A ratio about 1 means the reported covariance is right; large,
    that it is over-confident (unmodelled correlated errors). Cameras with fewer than 3
    successful solves are left out.
    """
    import dataclasses
    import logging

    method = getattr(opt, "jackknife_method", None) or METHOD
    if method not in ("linearised", "resolve"):
        raise ValueError(f"jackknife method: '{method}' is not linearised or resolve")
    if method == "linearised" and sol.graph is not None:
        return linearised_jackknife(sol)
    frames = sol.frames
    opt = dataclasses.replace(opt, progress=False, jackknife="never")
    package_log = logging.getLogger("calib3r_graph")
    level = package_log.level
    package_log.setLevel(logging.ERROR)  # the sub-solves repeat the main solve's warnings
    try:
        solves = leave_one_out_solves(ds, preds, opt, frames, solve_fn, progress)
    finally:
        package_log.setLevel(level)
    xis = {c: [X[c] for X, _ in solves.values() if c in X] for c in sol.ee_T_cam}
    fits = {f: fit for f, (_, fit) in solves.items() if fit}  # frame left out -> (robot chi2, dof) of that solve
    report = _jackknife_report(sol, xis)
    for rep in report.values():
        rep["method"] = "resolve"
    return report, influential_pose(sol.stats.get("noise_calibration", {}).get("robot_chi2_dof"), fits)


def leave_one_out_solves(ds, preds, opt, frames, solve_fn, progress=True) -> dict:
    """{frame: (ee_T_cam {camera: Pose3}, robot (chi2, dof) or None)} of the solve without each of
    ``frames`` (``solve_fn(ds, preds, opt)`` on the rest), for the solves that succeed, in the order
    of ``frames``.

    The solves are independent, so they run in up to ``opt.jobs`` forked processes (:func:`workers`):
    each is the same deterministic solve as in one process, so the numbers do not depend on how many
    run at once (tests/test_jackknife.py). The sample's 8 solves: 4.7 s in one process, 2.5 s in two
    on 2 cores (docs/uncertainty.md)."""
    import gtsam
    from tqdm import tqdm

    global _JOB
    n = workers(getattr(opt, "jobs", None), len(frames))
    bar = dict(total=len(frames), desc="jackknife", disable=None if progress else True, leave=False)
    with _JOB_LOCK:  # (one set of solves at a time reads _JOB)
        _JOB = (ds, preds, opt, list(frames), solve_fn)
        try:
            if n > 1:
                done = _in_processes(frames, n, bar)
            else:
                done = [_solve_without(f) for f in tqdm(frames, **bar)]
        finally:
            _JOB = None
    return {f: ({c: gtsam.Pose3(M) for c, M in r[0].items()}, r[1]) for f, r in done if r is not None}


_JOB = None  # (ds, preds, opt, frames, solve_fn) of the leave-one-out solves under way: what a forked worker reads
_JOB_LOCK = threading.Lock()


def _in_processes(frames, n: int, bar: dict) -> list:
    """``_solve_without`` of each frame in ``n`` forked processes, in the order of ``frames``.

    The workers ignore Ctrl-C: the parent's KeyboardInterrupt ends the pool, and the terminal's
    SIGINT to every process would print each worker's traceback. A worker that dies (the
    out-of-memory killer, a ``kill``) takes its solve with it, and ``Pool.imap`` would wait for
    that result for ever: the parent looks every ``POLL_S`` whether a worker it started has ended,
    and raises :class:`Calib3rError` naming it if one has."""
    import multiprocessing
    import signal

    from tqdm import tqdm

    from calib3r_graph.errors import Calib3rError

    ctx = multiprocessing.get_context("fork")
    before = set(multiprocessing.active_children())
    with ctx.Pool(n, initializer=_ignore_interrupt) as pool:
        started = set(multiprocessing.active_children()) - before  # this pool's workers
        results, done = pool.imap(_solve_without, frames), []
        with tqdm(**bar) as progress:
            while len(done) < len(frames):
                try:
                    done.append(results.next(timeout=POLL_S))
                    progress.update()
                    continue
                except multiprocessing.TimeoutError:
                    pass
                dead = sorted((p for p in started if not p.is_alive()), key=lambda p: p.pid)
                if dead:
                    code = dead[0].exitcode
                    how = f"was killed by {signal.Signals(-code).name}" if code is not None and code < 0 \
                        else f"exited with {code}"
                    raise Calib3rError(
                        f"jackknife: its worker process {dead[0].pid} {how} after {len(done)} of {len(frames)} "
                        "re-solves (the out-of-memory killer? `dmesg` says), and the solve stopped; run it again, "
                        "with --jobs 1 for one process")
    return done


POLL_S = 0.5  # how often the parent looks whether a worker has died (_in_processes)


def _ignore_interrupt():
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _solve_without(frame):
    """(frame, (ee_T_cam as 4x4 arrays, robot (chi2, dof)) of the solve without it, or None where it
    fails); the arrays pickle, for a worker process."""
    from calib3r_graph.errors import Calib3rError
    from calib3r_graph.io.dataset import subset_dataset
    from calib3r_graph.io.predictions import subset_predictions

    ds, preds, opt, frames, solve_fn = _JOB
    keep = [g for g in frames if g != frame]
    try:
        s = solve_fn(subset_dataset(ds, keep), subset_predictions(preds, keep), opt)
    except Calib3rError:
        return frame, None
    return frame, ({c: X.matrix() for c, X in s.ee_T_cam.items()}, s.stats["noise_calibration"].get("robot_chi2_dof"))


def workers(jobs, n: int) -> int:
    """How many processes run ``n`` independent solves: ``jobs`` (None: every CPU this process may
    use), at most n. One where a forked child is not safe or not allowed: off Linux (macOS's
    system libraries are not fork-safe, Windows has no fork) and inside a pool's worker (a daemon
    process may not have children)."""
    import multiprocessing
    import os
    import sys

    if not sys.platform.startswith("linux") or multiprocessing.current_process().daemon:
        return 1
    if jobs is None:
        jobs = len(os.sched_getaffinity(0))
    return max(1, min(int(jobs), n))


def linearised_jackknife(sol, system=None) -> tuple[dict, dict | None]:
    """:func:`jackknife` without re-solving: the same report from one linearisation of ``sol``'s graph.

    At the solution the whitened linear system ``sum_k ||A_k dx - b_k||^2`` has zero gradient,
    ``sum_k A_k^T b_k = 0``. Leaving frame i out removes the factors F_i that touch its views'
    variables (its robot pose and rigidity factors, its scene pairs, its depth-correction priors)
    and those variables; the first-order solution of the rest is

        dx_-i = H_-i^-1 (sum_{k not in F_i} A_k^T b_k) = -H_-i^-1 g_i,   H_-i = H - sum_{k in F_i} A_k^T A_k,

    on the remaining variables (H and g_i from each factor's augmented information, no tall A
    formed). The scale gauge factors (they tie lambda_j to every view's depth scale) are kept; they
    do not reach ee_T_cam. Robust weights and noise calibration are held at the full solve's: that
    is the approximation against the re-solving jackknife (measured in docs/uncertainty.md). The robot
    chi2 without frame i, ``sum ||A_k dx - b_k||^2`` over the remaining robot factors, feeds
    :func:`influential_pose` as the re-solves' chi2 does (the robot noise level cancels in its F).
    """
    graph = sol.graph if system is None else None  # (a live update's graph is built only where asked)
    out, fits, full = linearised_leave_one_out(graph, sol.values, sol.keys, list(sol.base_T_cam), system)
    xis = {c: [sol.ee_T_cam[c].retract(d[c]) for d in out.values()] for c in sol.ee_T_cam}
    report = _jackknife_report(sol, xis)
    for rep in report.values():
        rep["method"] = "linearised"
    return report, influential_pose(full, fits)


def factor_system(graph, values, offsets=None) -> tuple[np.ndarray, dict, list]:
    """(H, offsets, factors) of ``graph`` linearised at ``values``: the dense information matrix
    ``H = sum_k A_k^T A_k`` (whitened), {key: (first column, dimension)} in key order, and per factor
    (keys, its columns, A^T A, A^T b, b^T b), from each factor's augmented information (no tall A).
    ``offsets``: another graph's column layout (one that holds this graph's keys), for a part of it."""
    from calib3r_graph.solver.systematic import key_offsets

    lin = graph.linearize(values)
    offsets = key_offsets(graph, values) if offsets is None else offsets
    col = sum(d for _, d in offsets.values())
    H = np.zeros((col, col))
    factors = []
    for i in range(lin.size()):
        f = lin.at(i)
        if f is None:
            continue
        M = f.augmentedInformation()
        ks = list(f.keys())
        idx = np.concatenate([np.arange(offsets[k][0], offsets[k][0] + offsets[k][1]) for k in ks])
        d = len(idx)
        H[np.ix_(idx, idx)] += M[:d, :d]
        factors.append((ks, idx, M[:d, :d], M[:d, d], M[d, d]))
    return H, offsets, factors


def at_linear_minimum(system) -> tuple:
    """:func:`factor_system`'s ``system`` moved to the minimum of its own linear model: with
    ``dx = H^-1 sum_k A_k^T b_k``, each factor's ``b_k' = b_k - A_k dx`` (``A^T b`` and ``b^T b``
    updated without forming A). :func:`linearised_leave_one_out` assumes a zero total gradient; a
    solution that stopped short of it (one Gauss-Newton step of a live update) would otherwise put
    the full step's remainder into every sample."""
    H, offsets, factors = system
    g = np.zeros(len(H))
    for _, idx, _, Atb, _ in factors:
        g[idx] += Atb
    return moved_system(system, np.linalg.solve(H, g))


def moved_system(system, dx) -> tuple:
    """The same linear system about the point moved by ``dx``: per factor ``b' = b - A dx``."""
    H, offsets, factors = system
    return H, offsets, [(ks, idx, AtA, Atb - AtA @ dx[idx], btb - 2 * dx[idx] @ Atb + dx[idx] @ AtA @ dx[idx])
                        for ks, idx, AtA, Atb, btb in factors]


def linearised_leave_one_out(graph, values, keys, views, system=None, systems=None) -> tuple[dict, dict, tuple]:
    """({frame: {camera: dx of ee_T_cam (6,) without that frame}}, {frame: (robot chi2, dof)
    without it}, (robot chi2, dof) of all), as :func:`linearised_jackknife` describes. ``keys``: the
    graph's ``Keys``; ``views``: the solved view ids; ``system``: :func:`factor_system` of the graph
    about ``values``, if already computed. ``systems``: a dict to fill with {frame: (the kept
    columns, the Cholesky factor of H_-i on them, dx_-i on them)} for each sample, so that a caller
    can ask how a sample moves with more information (``solver/guidance.py``: a candidate pose's)."""
    from scipy.linalg import cho_factor, cho_solve  # triangular solves: general ones cost 4x (0.27 of 0.49 s)

    H, offsets, factors = system or factor_system(graph, values)
    n = len(H)
    gauge = {keys.metric(c) for c in keys.cameras}
    robot_keys = {(keys.hand_eye(split_view_id(v)[0]), keys.pose(v)) for v in views}
    factors = [(set(ks), idx, A, b, c, tuple(ks) in robot_keys) for ks, idx, A, b, c in factors]
    view_keys = {v: {k for k in (keys.pose(v), keys.scale(v), keys.correction(v)) if k in offsets} for v in views}
    by_frame = {}
    for v in views:
        by_frame.setdefault(split_view_id(v)[1], []).append(v)
    n_frames = len(by_frame)
    full = (float(sum(c for _, _, _, _, c, r in factors if r)), 6 * n_frames - 13)
    out, fits = {}, {}
    he = {c: keys.hand_eye(c) for c in keys.cameras if keys.hand_eye(c) in offsets}
    for frame, fviews in by_frame.items():
        gone_views = set(fviews) | _stranded_views(set(fviews), view_keys, keys, factors, gauge)
        left = {split_view_id(v)[1] for v in views if v not in gone_views}
        if len(left) < MIN_POSES:  # the re-solve would refuse: too few poses left
            continue
        fkeys = set().union(*(view_keys[v] for v in gone_views))
        drop = [fa for fa in factors if fa[0] & fkeys and not fa[0] & gauge]
        Hm, g = H.copy(), np.zeros(n)
        for _, idx, AtA, Atb, _, _ in drop:
            Hm[np.ix_(idx, idx)] -= AtA
            g[idx] += Atb
        gone = np.concatenate([np.arange(offsets[k][0], offsets[k][0] + offsets[k][1]) for k in fkeys])
        keep = np.setdiff1d(np.arange(n), gone)
        try:  # Cholesky: the rest must still determine every variable (else the re-solve fails too)
            cho = cho_factor(Hm[np.ix_(keep, keep)], lower=True, check_finite=False)
            dx_keep = -cho_solve(cho, g[keep], check_finite=False)
        except np.linalg.LinAlgError:
            continue
        dx = np.zeros(n)
        dx[keep] = dx_keep
        d_he = {c: dx[offsets[k][0]:offsets[k][0] + 6] for c, k in he.items()}
        if not all(np.all(np.isfinite(d)) and np.linalg.norm(d[:3]) < MAX_STEP[0] and np.linalg.norm(d[3:]) < MAX_STEP[1]
                   for d in d_he.values()):
            continue  # without this pose the rest (nearly) does not determine ee_T_cam: no sample
        out[frame] = d_he
        if systems is not None:
            systems[frame] = (keep, cho, dx_keep)
        if gone_views != set(fviews):  # influential_pose's F counts one pose's 6 residuals
            continue
        chi2 = sum(x @ A @ x - 2 * x @ b + c for ks, idx, A, b, c, r in factors if r and not ks & fkeys
                   for x in [dx[idx]])
        fits[frame] = (float(chi2), 6 * len(left) - 13)
    return out, fits, full


def _stranded_views(gone: set, view_keys: dict, keys, factors, gauge) -> set:
    """The other views left without any scene factor once the views ``gone`` are left out
    (repeated: dropping one can strand the next). A view's depth scale is touched only by its scene
    factors and the scale gauge, so a stranded one is fixed by the gauge alone and the downdated
    system is singular. The re-solve drops such a view ("solved without it", solver/views.py), and
    so does this: on rwhe_kuka_1's 10-pose subset 0003, 0006, ..., 0030, leaving 0008 out strands
    0020 (its only scene pair), and without this the linearised jackknife had 9 samples to 10."""
    scale = {keys.scale(v): v for v in view_keys if keys.scale(v) in view_keys[v]}
    out = set()
    while True:
        gone_keys = set().union(*(view_keys[v] for v in gone | out))
        alive = set()
        for ks, *_ in factors:
            if not ks & gauge and not ks & gone_keys:
                alive |= ks
        stranded = {v for k, v in scale.items() if k not in alive and v not in gone | out}
        if not stranded:
            return out
        out |= stranded


def _sigmas(X, C) -> dict:
    from calib3r_graph.io.results import covariance_in_ee_frame, sigma_ee_frame

    return sigma_ee_frame(np.sqrt(np.maximum(np.diag(covariance_in_ee_frame(X, np.asarray(C))), 0)))


def _jackknife_report(sol, xis) -> dict:
    import gtsam

    out = {}
    for c, xs in xis.items():
        if len(xs) < 3:
            continue
        X = sol.ee_T_cam[c]
        xs = np.array([gtsam.Pose3.Logmap(X.between(Y)) for Y in xs])
        n = len(xs)
        C = (n - 1) / n * (xs - xs.mean(0)).T @ (xs - xs.mean(0))
        jk, rep = _sigmas(X, C), _sigmas(X, sol.covariance[c])
        out[c] = {"solves": n, "covariance": C.tolist(), "sigma_jackknife": jk,
                  "ratio_to_reported": [jk[a] / rep[a] for a in AXES]}
    return out


def influential_pose(full, fits: dict, alpha=ALPHA) -> dict | None:
    """The pose without which the robot and the images agree significantly better, or None.

    Baarda's data snooping on the leave-one-out solves: for the pose k whose removal lowers the
    robot chi2 most, ``F = ((chi2 - chi2_k) / 6) / (chi2_k / dof_k)`` (6 = the pose's robot
    residual) is tested against F(6, dof_k) at ``alpha`` over all n poses (Bonferroni). The
    arm's overall noise level cancels in F; a wrong view or pose does not. ``full``: (chi2, dof)
    of the full solve; ``fits``: {frame: (chi2, dof)} without each."""
    from scipy.special import fdtrc  # F's survival function; scipy.stats would cost seconds to import

    if not full or not fits:
        return None
    chi2, dof = full
    frame, (chi2_k, dof_k) = min(fits.items(), key=lambda kv: kv[1][0] / max(kv[1][1], 1))
    if dof_k < 1 or chi2_k <= 0:
        return None
    F = ((chi2 - chi2_k) / 6) / (chi2_k / dof_k)
    p = float(fdtrc(6, dof_k, F))
    if p >= alpha / len(fits):
        return None
    return {"frame": frame, "F": float(F), "p": p, "chi2_per_dof": chi2 / dof, "chi2_per_dof_without": chi2_k / dof_k,
            "chi2_ratio": (chi2 / dof) / (chi2_k / dof_k)}


def cover(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The covariance that covers both A and B: in the frame where A is the identity
    (``L^-1 B L^-T``, ``A = L L^T``), B's eigenvalues below 1 are raised to 1. The result minus A
    and minus B are both positive semi-definite, and it equals A wherever B is smaller."""
    try:
        L = np.linalg.cholesky(A)
    except np.linalg.LinAlgError:  # A not positive definite (numerically): the sum covers both too
        return A + B
    Li = np.linalg.inv(L)
    w, V = np.linalg.eigh(Li @ B @ Li.T)
    M = L @ V @ np.diag(np.maximum(w, 1.0)) @ V.T @ L.T
    return 0.5 * (M + M.T)
