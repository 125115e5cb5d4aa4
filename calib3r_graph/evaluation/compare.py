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
runs under one guard (:func:`run_method`, then guard.board_check; the checks live in guard.py): a
library exception, a failure OpenCV only prints, a non-finite result, a reflection, a flange motion
that cannot fix the hand-eye, and a result whose own AX = XB residual on the board is absurd are
"failed: <reason>", never "ok".
"""

import dataclasses
import logging
import tempfile
import time
from pathlib import Path

import gtsam
import numpy as np

from calib3r_graph.errors import Calib3rError, SolveError
from calib3r_graph.evaluation.guard import (PATTERN_METHODS, MethodFailed, board_check, check_flange_motion,
                                            check_pattern_ba, check_result, guarded, rotates_about_two_axes)
from calib3r_graph.geometry import hand_eye_rotation
from calib3r_graph.io.dataset import ee_T_cam_by_camera, subset_dataset
from calib3r_graph.io.predictions import Predictions, split_view_id, subset_predictions
from calib3r_graph.io.results import uncertainty_report

log = logging.getLogger(__name__)

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


def run_method(name, ds, preds, noise, frames=None, detections=None, hold_intrinsics=False):
    """({camera: ee_T_cam}, {camera: 6x6 covariance}) of one method on the given frames (all if
    None); the covariance is empty for methods that do not estimate one.

    Under the guard every method shares: SolveError when the method cannot run (no pattern, no
    predictions); MethodFailed when it breaks on the data (an OpenCV or GTSAM exception, a failure
    OpenCV only prints) or returns what cannot be right (check_result, a motion about fewer than
    two axes, pattern-ba's corner noise far above the PnP fit's).

    ``detections``: a dict shared between calls, so the board is detected once per frame set.
    """
    return guarded(lambda: _run_method(name, ds, preds, noise, frames, detections, hold_intrinsics), ds.base_T_ee,
                   capture_printed=name in PATTERN_METHODS)


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
            check_flange_motion(sub.base_T_ee, poses)
        init = {c: pattern.opencv_hand_eye(sub, d, "park") for c, d in dets.items()}
        check_result(init, {})  # a broken start is not pattern-ba's answer
        res = pattern.pattern_ba(sub, dets, noise, init, refine_intrinsics=not hold_intrinsics)
        check_pattern_ba(res, dets)
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
    results, detections, solved, covariances = {}, {}, {}, {}
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
            covariances[m] = {c: C for c, C in cov.items() if c in X}
        if ("metric_scale", m) in detections:  # the reconstruction's δ_s, where the method has one
            results[m]["metric_scale"] = detections.pop(("metric_scale", m))
        log.info("%s: %s (%.1f s)", m, status, results[m]["seconds"])
    out = {"methods": results}
    if key in detections and solved:
        check = board_check(sub, detections[key], solved, noise, covariances)
        for m, reason in check["failed"].items():
            results[m].update(cameras={}, status=f"failed: {reason}")
            log.warning("%s: failed: %s", m, reason)
        for m, res in check["residuals"].items():
            results[m]["board_residual"] = res
        out["board_allows"] = check["allows"]
    return out


def _first_line(e) -> str:
    return str(e).splitlines()[0] if str(e) else type(e).__name__


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
