"""``compare``: every method calibration engineers use, on the same data, timed.

Methods (names as written to comparison.json):
  tsai, park, horaud, andreff, daniilidis  OpenCV's closed-form solvers on the pattern (detection + PnP)
  pattern-ba       joint reprojection adjustment over ee_T_cam, base_T_board and the views (pattern.py)
  jcr-colmap       two-stage: a pycolmap trajectory, then hand-eye with the metric scale found by a
                   grid search over the scale (as JCR does)
  jcr-predictions  the same two stages on the trajectory from our predictions (pairwise Sim(3) +
                   spanning tree), without the joint graph
  calib3r-graph    ours
A method that cannot run (no pattern, no images) is reported with status "error: ...". Every method
runs under one guard (:func:`run_method`, :func:`board_check`): a library exception, a failure OpenCV
only prints, a non-finite result, a reflection, a flange motion that cannot fix the hand-eye, and a
result whose own AX = XB residual on the board is absurd are "failed: <reason>", never "ok".
"""

import contextlib
import dataclasses
import logging
import os
import re
import sys
import tempfile
import time
from pathlib import Path

import gtsam
import numpy as np

from calib3r_graph.errors import Calib3rError, SolveError, library_error
from calib3r_graph.geometry import hand_eye_rotation
from calib3r_graph.io.dataset import ee_T_cam_by_camera, subset_dataset
from calib3r_graph.io.predictions import Predictions, split_view_id, subset_predictions
from calib3r_graph.io.results import uncertainty_report

log = logging.getLogger(__name__)

PATTERN_METHODS = ["tsai", "park", "horaud", "andreff", "daniilidis", "pattern-ba"]
METHODS = ["tsai", "park", "horaud", "andreff", "daniilidis", "pattern-ba", "jcr-colmap", "jcr-predictions",
           "calib3r-graph"]


def two_stage_hand_eye(trajectory: dict, base_T_ee: dict, scales=np.logspace(-4, 4, 161)) -> dict:
    """JCR-style: a fixed visual trajectory {view: world_T_cam (Pose3, unknown scale)}; per camera the
    rotation from AX = XB (Kabsch on motion axes), then the scale by grid search (coarse, then two
    finer grids around the best), translation by least squares at each scale."""
    by_cam = {}
    for v, T in trajectory.items():
        by_cam.setdefault(split_view_id(v)[0], []).append((split_view_id(v)[1], T))
    out = {}
    for cam, vs in by_cam.items():
        pairs = [(a, b) for i, a in enumerate(vs) for b in vs[i + 1:]]
        A = [base_T_ee[a[0]].between(base_T_ee[b[0]]) for a, b in pairs]
        B = [a[1].between(b[1]) for a, b in pairs]
        rot = [(gtsam.Rot3.Logmap(x.rotation()), gtsam.Rot3.Logmap(y.rotation())) for x, y in zip(A, B)
               if np.linalg.norm(gtsam.Rot3.Logmap(y.rotation())) > np.radians(1)]
        if len(rot) < 2:
            raise SolveError(f"{cam}: fewer than two rotating motions in the trajectory")
        R_X, _ = hand_eye_rotation(*map(np.array, zip(*rot)))
        M = np.vstack([x.rotation().matrix() - np.eye(3) for x in A])
        tA = np.concatenate([x.translation() for x in A])
        RtB = np.concatenate([R_X @ y.translation() for y in B])

        def fit(lam):
            t, *_ = np.linalg.lstsq(M, lam * RtB - tA, rcond=None)
            return np.linalg.norm(M @ t - (lam * RtB - tA)), t

        grid = scales
        for _ in range(3):
            res = [fit(l)[0] for l in grid]
            k = int(np.argmin(res))
            lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
            grid = np.linspace(lo, hi, 101)
        lam = grid[int(np.argmin([fit(l)[0] for l in grid]))]
        out[cam] = gtsam.Pose3(gtsam.Rot3(R_X), fit(lam)[1])
    return out


class MethodFailed(SolveError):
    """A method ran, and what it returned cannot be right (compare reports "failed: <reason>")."""


# A result is absurd when it fits its own data this many times worse than the data allow: the
# per-image fit (PnP) for pattern-ba's corner noise, the noise of PnP and of the robot and the best
# method for the AX = XB residual. Valid methods fit the same equations, so they differ by a small
# factor: on rwhe_kuka_1 and tabb_ds1, whole and halved, every pattern method's rotation residual is
# 1.2-2.1x the predicted noise and its translation residual within 2.4x of the best method's
# (docs/compare.md). A wrong answer (a flipped board, a solver that gave up) is 1000x off.
ABSURD_FACTOR = 10.0
# OpenCV reports some failures only by printing them (calibrateHandEye's Tsai returns R = I, t = 0
# after "Hand-eye calibration failed! Not enough informative motions--include larger rotations.").
PRINTED_FAILURE = re.compile(r"[\w-]*\s*calibration failed[^\n]*", re.IGNORECASE)
# What a method can raise when it breaks on the data (OpenCV, GTSAM's RuntimeError, numpy);
# anything else is a bug and is not hidden.
METHOD_EXCEPTIONS = (np.linalg.LinAlgError, RuntimeError, ValueError, ArithmeticError)


@contextlib.contextmanager
def printed_output():
    """Capture what libraries print on stdout and stderr inside the block, at the file-descriptor
    level (C++ code writes there, past Python's sys.stdout); yields a list that holds the text
    afterwards. The text is passed on to stderr, so nothing the user would have seen is lost."""
    sys.stdout.flush()
    sys.stderr.flush()
    out = []
    try:
        saved = [os.dup(1), os.dup(2)]
    except OSError:  # no standard descriptors to capture (a closed stdout): nothing printed can be read
        yield [""]
        return
    with tempfile.TemporaryFile() as tmp:
        try:
            os.dup2(tmp.fileno(), 1)
            os.dup2(tmp.fileno(), 2)
            yield out
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            tmp.seek(0)
            out.append(tmp.read().decode(errors="replace"))
            if out[0]:
                sys.stderr.write(out[0])
                sys.stderr.flush()


def _exception_reason(e) -> str:
    described = library_error(e)
    if described is not None:
        return described[0]
    first = next((line.strip() for line in str(e).splitlines() if line.strip()), "")
    return f"{type(e).__name__}: {first}" if first else type(e).__name__


def check_result(X: dict, cov: dict):
    """MethodFailed unless every camera's ee_T_cam is finite and a rotation (det R = +1, R^T R = I,
    within 1e-6) and every covariance is finite."""
    for c, T in X.items():
        M = np.asarray(T.matrix())
        if not np.all(np.isfinite(M)):
            raise MethodFailed(f"{c}: the result is not finite (NaN or inf in ee_T_cam)")
        R = M[:3, :3]
        det = float(np.linalg.det(R))
        if abs(det - 1) > 1e-6 or np.abs(R.T @ R - np.eye(3)).max() > 1e-6:
            raise MethodFailed(f"{c}: the result is " + (f"a reflection (det R = {det:.3f})" if det < 0 else
                                                         f"not a rotation (det R = {det:.6f})"))
    for c, C in cov.items():
        if not np.all(np.isfinite(np.asarray(C))):
            raise MethodFailed(f"{c}: its covariance is not finite (±inf or NaN sigmas)")


def _check_motion(base_T_ee: dict, frames):
    if not rotates_about_two_axes(base_T_ee, frames):
        raise MethodFailed(f"the flange rotates about fewer than two axes among the {len(set(frames))} poses it "
                           "used: AX = XB leaves the hand-eye undetermined")


def run_method(name, ds, preds, noise, frames=None, detections=None, hold_intrinsics=False):
    """({camera: ee_T_cam}, {camera: 6x6 covariance}) of one method on the given frames (all if
    None); the covariance is empty for methods that do not estimate one.

    Under the guard every method shares: SolveError when the method cannot run (no pattern, no
    predictions); MethodFailed when it breaks on the data (an OpenCV or GTSAM exception, a failure
    OpenCV only prints) or returns what cannot be right (check_result, a motion about fewer than
    two axes, pattern-ba's corner noise far above the PnP fit's).

    ``detections``: a dict shared between calls, so the board is detected once per frame set.
    """
    try:
        with printed_output() if name in PATTERN_METHODS else contextlib.nullcontext([""]) as printed:
            X, cov, used = _run_method(name, ds, preds, noise, frames, detections, hold_intrinsics)
    except Calib3rError:
        raise
    except METHOD_EXCEPTIONS + _library_exceptions() as e:
        raise MethodFailed(_exception_reason(e)) from e
    said = PRINTED_FAILURE.search(printed[0] if printed else "")
    if said:
        raise MethodFailed(f"OpenCV printed '{said.group(0).strip()}'")
    for poses in used:  # the frames each camera's result rests on (the board's, for the pattern methods)
        _check_motion(ds.base_T_ee, poses)
    check_result(X, cov)
    return X, cov


def _library_exceptions() -> tuple:
    import cv2

    return (cv2.error,)


def _run_method(name, ds, preds, noise, frames, detections, hold_intrinsics):
    from calib3r_graph.evaluation import pattern

    sub = subset_dataset(ds, frames) if frames is not None else ds
    if name in pattern.OPENCV_METHODS or name == "pattern-ba":
        if not ds.pattern:
            raise SolveError("no pattern in dataset.yaml")
        detections = {} if detections is None else detections
        key = tuple(sub.base_T_ee)
        if key not in detections:
            t = time.perf_counter()
            detections[key] = {c: pattern.detect(sub, c) for c in sub.cameras}
            detections[("seconds",) + key] = time.perf_counter() - t
        dets = {c: d for c, d in detections[key].items() if len(d) >= 3}
        if not dets:
            raise SolveError("the board is not found in enough images")
        used = [[x.frame for x in d] for d in dets.values()]
        if name != "pattern-ba":
            return {c: pattern.opencv_hand_eye(sub, d, name) for c, d in dets.items()}, {}, used
        for poses in used:  # before park's start, which a degenerate motion makes NaN
            _check_motion(sub.base_T_ee, poses)
        init = {c: pattern.opencv_hand_eye(sub, d, "park") for c, d in dets.items()}
        check_result(init, {})  # a broken start is not pattern-ba's answer
        res = pattern.pattern_ba(sub, dets, noise, init, refine_intrinsics=not hold_intrinsics)
        _check_pattern_ba(res, dets)
        return res.ee_T_cam, res.covariance, used
    if name == "jcr-colmap":
        from calib3r_graph.frontends.colmap import colmap_trajectory

        traj = colmap_trajectory(sub)
        return two_stage_hand_eye({v: gtsam.Pose3(T) for v, T in traj.items()}, sub.base_T_ee), {}, \
            [[split_view_id(v)[1] for v in traj]]
    if preds is None:
        raise SolveError("no predictions")
    p = subset_predictions(preds, sub.base_T_ee) if frames is not None else preds
    if name == "jcr-predictions":
        from calib3r_graph.solver.init import pairwise_sim3, spanning_tree_poses
        from calib3r_graph.solver.observations import build_observations

        obs = build_observations(p)
        comps = spanning_tree_poses(sorted(p.views), obs, pairwise_sim3(obs))
        if not comps:
            raise SolveError("no predicted views for these frames")
        biggest = max(comps, key=len)
        return two_stage_hand_eye({v: T for v, (T, _) in biggest.items()}, sub.base_T_ee), {}, \
            [[split_view_id(v)[1] for v in biggest]]
    if name == "calib3r-graph":
        from calib3r_graph.solver.solve import SolveOptions, solve

        sol = solve(sub, p, SolveOptions(noise=noise, progress=False))
        if frames is None and ds.pattern and detections is not None:
            _metric_scale(name, sub, p, sol, detections)
        return sol.ee_T_cam, sol.covariance, []  # solve checks its own motion (uncertainty.check_motion)
    raise ValueError(name)


def _check_pattern_ba(res, dets: dict):
    """pattern-ba's calibrated corner noise against the per-image PnP fit's (which fits each image
    alone, so it is the least the corners allow): a joint fit ABSURD_FACTOR x worse, or not finite,
    has not found a mount that explains the images."""
    uv_rms = np.sqrt(np.mean([d.reprojection_px ** 2 for ds_ in dets.values() for d in ds_]))
    figures = [res.corner_sigma_px, res.robot_noise_factor, res.board_scale]
    if not np.all(np.isfinite(figures)):
        raise MethodFailed(f"non-finite fit (corner noise {res.corner_sigma_px:.3g} px, robot poses "
                           f"{res.robot_noise_factor:.3g}x their sigma, board scale {res.board_scale:.3g})")
    if res.corner_sigma_px > ABSURD_FACTOR * uv_rms:
        raise MethodFailed(f"corner noise {res.corner_sigma_px:.3g} px is {res.corner_sigma_px / uv_rms:.0f}x the "
                           f"per-image PnP fit's {uv_rms:.3g} px: no mount explains the images and the poses")


def _metric_scale(name, ds, preds, sol, detections):
    """The paper's δ_s of a method's reconstruction (evaluate.metric_scale_accuracy), left in
    ``detections`` for compare(), with its time, which is not the method's."""
    from calib3r_graph.evaluation import pattern
    from calib3r_graph.evaluation.evaluate import metric_scale_accuracy

    t = time.perf_counter()
    key = tuple(ds.base_T_ee)
    if key not in detections:
        detections[key] = {c: pattern.detect(ds, c) for c in ds.cameras}
        detections[("seconds",) + key] = time.perf_counter() - t
    try:
        detections[("metric_scale", name)] = metric_scale_accuracy(ds, preds, sol, detections[key])
    except Calib3rError as e:
        detections[("metric_scale", name)] = {"status": f"error: {e}"}
    detections[("metric_scale_seconds", name)] = time.perf_counter() - t


def compare(ds, preds, noise, methods=METHODS, frames=None, hold_intrinsics=False) -> dict:
    """Every method on the same frames; ``hold_intrinsics``: pattern-ba keeps the dataset's camera
    model instead of refining it (used on halves: the camera is the same camera). A method that
    cannot run has status "error: ...", one whose result cannot be right "failed: ..." (run_method,
    board_check); either way the others go on."""
    results, detections, solved = {}, {}, {}
    sub = subset_dataset(ds, frames) if frames is not None else ds
    key = tuple(sub.base_T_ee)
    for m in methods:
        t = time.perf_counter()
        try:
            X, cov = run_method(m, ds, preds, noise, frames, detections, hold_intrinsics)
            status = "ok" if X else "error: no camera could be calibrated"
        except MethodFailed as e:
            X, cov, status = {}, {}, f"failed: {_first_line(e)}"
        except Calib3rError as e:
            X, cov, status = {}, {}, f"error: {_first_line(e)}"
        seconds = time.perf_counter() - t - detections.pop(("metric_scale_seconds", m), 0.0)
        if m in PATTERN_METHODS and ("seconds",) + key in detections and seconds < detections[("seconds",) + key]:
            seconds += detections[("seconds",) + key]  # every pattern method pays the (shared) board detection
        cams = {c: {"T_ee_cam": x.matrix().tolist()} for c, x in X.items()}
        for c, C in cov.items():  # the method's own uncertainty, where it has one (per axis, ee frame)
            cams[c]["sigma_ee_frame"] = uncertainty_report(X[c], C)["sigma_ee_frame"]
        results[m] = {"cameras": cams, "seconds": seconds, "status": status}
        if X:
            solved[m] = X
        if ("metric_scale", m) in detections:  # the reconstruction's δ_s, where the method has one
            results[m]["metric_scale"] = detections.pop(("metric_scale", m))
        log.info("%s: %s (%.1f s)", m, status, results[m]["seconds"])
    out = {"methods": results}
    if key in detections and solved:
        check = board_check(sub, detections[key], solved, noise)
        for m, reason in check["failed"].items():
            results[m].update(cameras={}, status=f"failed: {reason}")
            log.warning("%s: failed: %s", m, reason)
        for m, res in check["residuals"].items():
            results[m]["board_residual"] = res
        out["board_allows"] = check["allows"]
    return out


def _first_line(e) -> str:
    return str(e).splitlines()[0] if str(e) else type(e).__name__


def board_residuals(base_T_ee: dict, dets: list, X) -> tuple[float, float]:
    """A result's own AX = XB residual on the board: the RMS rotation (rad) and translation (m) of
    ``base_T_board_i = base_T_ee_i ee_T_cam cam_T_board_i`` (each image's PnP) about their mean. The
    board does not move, so the right ee_T_cam makes them one pose up to the noise of PnP and robot."""
    from calib3r_graph.geometry import mean_pose

    P = [base_T_ee[d.frame].compose(X).compose(d.cam_T_board) for d in dets]
    M = mean_pose(P)
    dev = [M.between(p) for p in P]
    rot = np.sqrt(np.mean([np.sum(gtsam.Rot3.Logmap(d.rotation()) ** 2) for d in dev]))
    return float(rot), float(np.sqrt(np.mean([np.sum(d.translation() ** 2) for d in dev])))


def board_noise(ds, camera: str, dets: list, noise) -> tuple[float, float]:
    """What the board allows that residual to be with the right ee_T_cam: the RMS rotation (rad) and
    translation (m) spread of base_T_board from each image's PnP covariance (its Jacobian, scaled by
    the image's own reprojection error) and the robot's nominal noise (``noise``; the flange's rotation
    error moves the board by its distance)."""
    import cv2

    from calib3r_graph.evaluation.pattern import board_points

    cam, obj_all = ds.cameras[camera], board_points(ds.pattern)
    var_r, var_t = [], []
    for d in dets:
        obj = obj_all if d.ids is None else obj_all[np.asarray(d.ids)]
        rvec, _ = cv2.Rodrigues(d.cam_T_board.rotation().matrix())
        _, J = cv2.projectPoints(obj, rvec, d.cam_T_board.translation(), cam.K, cam.dist)
        J = J[:, :6]
        n = len(obj)
        sigma2 = d.reprojection_px ** 2 * n / max(2 * n - 6, 1)  # per image coordinate, less PnP's 6 dof
        C = sigma2 * np.linalg.pinv(J.T @ J)
        lever = np.linalg.norm(d.cam_T_board.translation())
        var_r.append(np.trace(C[:3, :3]) + 3 * np.radians(noise.robot_sigma_deg) ** 2)
        var_t.append(np.trace(C[3:, 3:]) + 3 * (noise.robot_sigma_mm * 1e-3) ** 2
                     + 2 * (lever * np.radians(noise.robot_sigma_deg)) ** 2)
    return float(np.sqrt(np.mean(var_r))), float(np.sqrt(np.mean(var_t)))


def board_check(ds, detections: dict, solved: dict, noise) -> dict:
    """The guard's last part, on the board's motion (needs every method's result): per camera, each
    result's AX = XB residual (board_residuals) against what the board allows, which is the larger of
    the PnP and robot noise (board_noise) and the best method's residual. A result ABSURD_FACTOR x
    beyond it has failed; so has one whose rotation residual is ABSURD_FACTOR x the noise alone (the
    rotation part needs no scale, unit or robot translation accuracy), even when every method is
    that far off (a flipped board, mispaired images). Methods that do not use the board are judged
    by it only where some pattern method fits it.

    Returns ``{"failed": {method: reason}, "residuals": {method: {camera: {"rotation_deg",
    "translation_mm"}}}, "allows": {camera: {"rotation_deg", "translation_mm", "noise_rotation_deg",
    "noise_translation_mm", "best"}}}``."""
    failed, residuals, allows = {}, {}, {}
    for c, dets in detections.items():
        if len(dets) < 3:
            continue
        res = {m: board_residuals(ds.base_T_ee, dets, X[c]) for m, X in solved.items() if c in X}
        if not res:
            continue
        n_rot, n_t = board_noise(ds, c, dets, noise)
        fits = {m for m, (r, _) in res.items() if r <= ABSURD_FACTOR * n_rot}
        board_fits = bool(fits & set(PATTERN_METHODS))  # some method that uses the board fits it
        judged = {m for m in res if m in PATTERN_METHODS or board_fits}
        best = min(fits, key=lambda m: res[m][0] / n_rot + res[m][1] / n_t) if fits else None
        a_rot, a_t = (max(n_rot, res[best][0]), max(n_t, res[best][1])) if best else (n_rot, n_t)
        allows[c] = {"rotation_deg": float(np.degrees(a_rot)), "translation_mm": a_t * 1e3,
                     "noise_rotation_deg": float(np.degrees(n_rot)), "noise_translation_mm": n_t * 1e3,
                     "best": best}
        for m, (r, t) in res.items():
            residuals.setdefault(m, {})[c] = {"rotation_deg": float(np.degrees(r)), "translation_mm": t * 1e3}
            if m not in judged or m in failed:
                continue
            what = f"{c}: its own AX = XB residual on the board is {np.degrees(r):.3g} deg / {t * 1e3:.3g} mm RMS"
            if m not in fits:
                failed[m] = (f"{what}, {r / n_rot:.0f}x the {np.degrees(n_rot):.2g} deg that the PnP and robot "
                             "noise allow (a flipped board, mispaired images and poses, or a solver that gave up)")
            elif r > ABSURD_FACTOR * a_rot or t > ABSURD_FACTOR * a_t:
                failed[m] = (f"{what}, {max(r / a_rot, t / a_t):.0f}x what the board allows ({np.degrees(a_rot):.2g} "
                             f"deg / {a_t * 1e3:.2g} mm: the best method, {best}, or the PnP and robot noise)")
    return {"failed": failed, "residuals": residuals, "allows": allows}


def errors_against(result: dict, reference: dict) -> dict:
    """{method: {camera: (e_t m, e_theta rad)}} against {camera: Pose3}."""
    from calib3r_graph.geometry import pose_error

    out = {}
    for m, r in result["methods"].items():
        out[m] = {}
        for c, X in ee_T_cam_by_camera(r["cameras"]).items():
            if c in reference:
                et, er = pose_error(X, reference[c])
                out[m][c] = (et, np.radians(er))
    return out


def markdown_table(result: dict, reference: dict, reference_name: str) -> str:
    errs = errors_against(result, reference)
    cams = sorted({c for e in errs.values() for c in e})
    head = "| method | " + " | ".join(f"{c} e_t (cm) | {c} e_θ (rad)" for c in cams) + " | time (s) | status |"
    lines = [f"Errors against {reference_name} (the paper's e_t in cm and e_θ in rad).", "", head,
             "|---|" + "---|---|" * len(cams) + "---|---|"]
    for m, r in result["methods"].items():
        cells = []
        for c in cams:
            e = errs[m].get(c)
            cells += [f"{e[0] * 100:.3f}", f"{e[1]:.5f}"] if e else ["–", "–"]
        lines.append(f"| {m} | " + " | ".join(cells) + f" | {r['seconds']:.1f} | {r['status']} |")
    return "\n".join(lines) + "\n"


def bar_plot(result: dict, reference: dict, path: Path, title: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    errs = errors_against(result, reference)
    names = [m for m in result["methods"] if errs.get(m)]
    et = [np.mean([e[0] for e in errs[m].values()]) * 1e3 for m in names]
    er = [np.degrees(np.mean([e[1] for e in errs[m].values()])) for m in names]
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for a, vals, lab in ((ax[0], et, "e_t (mm)"), (ax[1], er, "e_θ (deg)")):
        bars = a.bar(names, vals, color=["tab:red" if n == "calib3r-graph" else "tab:gray" for n in names])
        a.set_yscale("log")
        a.set_ylabel(lab)
        a.tick_params(axis="x", rotation=45)
        a.bar_label(bars, fmt="%.3g", fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def halves(ds, preds, noise, methods) -> dict:
    """Each method solved on the first and on the second half of the frames (recording order).

    Without ground truth this is the honest measure of how far to trust a method's result: a
    bias that every pose shares (robot kinematics, a camera model) moves it by an amount that
    depends on which poses were recorded, which no sigma and no leave-one-out jackknife shows.
    The two halves usually cover different parts of the workspace. pattern-ba keeps the dataset's
    camera model on each half (the camera is the same on both; refining it on half the poses
    lets the focal length absorb robot error: rwhe_kuka_1's first half moved fx 0.2 % and the
    hand-eye 11 mm). Returns ``{"frames": [first, second], "methods": {NAME: {"cameras": {CAM:
    {"e_t_m", "e_theta_rad"}}, "status"}}, "in_sigmas": the difference per ee axis in sigmas of
    a difference (consistency.py), "halves": both compare() results}``.
    """
    frames = list(ds.frames)
    split = [frames[:len(frames) // 2], frames[len(frames) // 2:]]
    first, second = (compare(ds, preds, noise, methods, f, hold_intrinsics=True) for f in split)
    out = {}
    for m in methods:
        a, b = first["methods"][m], second["methods"][m]
        bad = [f"{h} half: {r['status']}" for h, r in (("first", a), ("second", b)) if r["status"] != "ok"]
        errs = errors_against({"methods": {m: a}}, ee_T_cam_by_camera(b["cameras"]))[m] if not bad else {}
        out[m] = {"cameras": {c: {"e_t_m": et, "e_theta_rad": er} for c, (et, er) in errs.items()},
                  "status": "; ".join(bad) or "ok"}
    from calib3r_graph.evaluation.consistency import halves_consistency

    return {"frames": split, "methods": out, "in_sigmas": halves_consistency(first, second),
            "halves": {"first": first, "second": second}}


def halves_table(result: dict) -> str:
    cams = sorted({c for r in result["methods"].values() for c in r["cameras"]})
    f1, f2 = result["frames"]
    lines = [f"Each method on frames {f1[0]}-{f1[-1]} against itself on frames {f2[0]}-{f2[-1]} "
             "(e_t in cm, e_θ in rad).", "",
             "| method | " + " | ".join(f"{c} e_t (cm) | {c} e_θ (rad)" for c in cams) + " | status |",
             "|---|" + "---|---|" * len(cams) + "---|"]
    for m, r in result["methods"].items():
        cells = []
        for c in cams:
            e = r["cameras"].get(c)
            cells += [f"{e['e_t_m'] * 100:.3f}", f"{e['e_theta_rad']:.5f}"] if e else ["–", "–"]
        lines.append(f"| {m} | " + " | ".join(cells) + f" | {r['status']} |")
    return "\n".join(lines) + "\n"


def rotates_about_two_axes(base_T_ee: dict, frames, min_angle_deg=5.0, min_axis_deg=20.0) -> bool:
    """Whether the flange's relative motions among ``frames`` include two rotations of at least
    ``min_angle_deg`` about axes at least ``min_axis_deg`` apart (in the flange frame): what
    AX = XB needs to fix the hand-eye rotation and translation."""
    from calib3r_graph.solver.uncertainty import relative_rotations

    w = relative_rotations(base_T_ee, list(frames))
    norm = np.linalg.norm(w, axis=1)
    axes = w[norm >= np.radians(min_angle_deg)] / norm[norm >= np.radians(min_angle_deg), None]
    if len(axes) < 2:
        return False
    return bool(np.abs(axes @ axes.T).min() <= np.cos(np.radians(min_axis_deg)))


def random_subsets(ds, n: int, repeats: int, seed=0, max_draws=10000) -> list:
    """``repeats`` distinct, seeded random subsets of ``n`` frames (recording order) whose flange
    motions rotate about at least two axes; fewer if the recording has fewer such subsets."""
    rng = np.random.default_rng([seed, n])
    frames = list(ds.frames)
    out, seen = [], set()
    for _ in range(max_draws):
        if len(out) == repeats or n > len(frames):
            break
        pick = tuple(frames[i] for i in sorted(rng.choice(len(frames), n, replace=False)))
        if pick in seen:
            continue
        seen.add(pick)
        if rotates_about_two_axes(ds.base_T_ee, pick):
            out.append(list(pick))
    return out


def views_sweep(ds, preds, noise, views_list, repeats, methods, reference, seed=0, predict_subset=None) -> dict:
    """Errors of every method against the number of robot poses, over seeded random subsets that
    rotate about at least two axes (:func:`random_subsets`). Every run is a row; a method that
    fails on a subset gives a row with its status and no errors, so solve rates can be counted.

    ``predict_subset(frames) -> Predictions``: the predictions made from the subset's images
    alone. By default, predictions of the pairwise frontend are re-made per subset this way
    (:func:`subset_predictor`); others (colmap, a foundation model's) are the full recording's,
    restricted to the subset, so their depth saw the other frames too."""
    with tempfile.TemporaryDirectory(prefix="calib3r-sweep-") as cache:
        if predict_subset is None:
            predict_subset = subset_predictor(ds, preds, cache)
        return _views_sweep(ds, preds, noise, views_list, repeats, methods, reference, seed, predict_subset)


def subset_predictor(ds, preds, cache_dir):
    """For predictions made by the pairwise frontend: ``frames -> Predictions`` from those frames'
    images alone, with the frontend's options (features and pair geometries cached in
    ``cache_dir``, so each is computed once per sweep). None for other predictions."""
    if preds is None or not str(preds.info.get("source", "")).startswith("calib3r-graph pairwise"):
        return None
    from calib3r_graph.frontends.pairwise import PairwiseOptions, pairwise_predictions

    known = {f.name for f in dataclasses.fields(PairwiseOptions)}
    opt = PairwiseOptions(**{k: v for k, v in preds.info.get("options", {}).items() if k in known})
    return lambda frames: pairwise_predictions(subset_dataset(ds, frames), opt=opt, cache_dir=cache_dir,
                                               progress=False, name=preds.name)


def _views_sweep(ds, preds, noise, views_list, repeats, methods, reference, seed, predict_subset) -> dict:
    rows = []
    for n in views_list:
        for r, sub in enumerate(random_subsets(ds, n, repeats, seed)):
            p = preds
            if predict_subset is not None:
                try:
                    p = predict_subset(sub)
                except (Calib3rError, RuntimeError, ValueError) as e:
                    p = None
                    log.warning("frames %s: no predictions (%s)", ",".join(sub), e)
            res = compare(ds, p, noise, methods, sub)
            errs = errors_against(res, reference)
            for m, r_m in res["methods"].items():
                for c, (et, er) in errs.get(m, {}).items():
                    rows.append({"views": n, "repeat": r, "frames": sub, "method": m, "camera": c, "e_t_m": et,
                                 "e_theta_rad": er, "status": r_m["status"]})
                if not errs.get(m):
                    rows.append({"views": n, "repeat": r, "frames": sub, "method": m, "camera": None,
                                 "e_t_m": None, "e_theta_rad": None, "status": r_m["status"]})
    return {"rows": rows}


def sweep_plot(sweep: dict, path: Path, reference_name: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in sweep["rows"] if r.get("e_t_m") is not None]  # failed runs have no errors
    methods = sorted({r["method"] for r in rows}, key=METHODS.index)
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for m in methods:
        ns = sorted({r["views"] for r in rows if r["method"] == m})
        for a, key, scale in ((ax[0], "e_t_m", 1e2), (ax[1], "e_theta_rad", 1.0)):
            vals = [[r[key] * scale for r in rows if r["method"] == m and r["views"] == n] for n in ns]
            # median and quartiles: a few failed-looking subsets must not hide the typical error
            med = np.array([np.median(v) for v in vals])
            lo, hi = (np.array([np.percentile(v, q) for v in vals]) for q in (25, 75))
            a.errorbar(ns, med, yerr=[med - lo, hi - med], marker="o", capsize=2,
                       label=m, lw=2.5 if m == "calib3r-graph" else 1)
    ax[0].set_ylabel(f"e_t (cm) vs {reference_name}")
    fig.suptitle("median and quartiles over random subsets rotating about two axes", fontsize=9)
    ax[1].set_ylabel(f"e_θ (rad) vs {reference_name}")
    for a in ax:
        a.set_xlabel("number of robot poses")
        a.set_yscale("log")
    ax[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
