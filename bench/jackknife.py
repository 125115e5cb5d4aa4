"""Linearised vs re-solving leave-one-pose-out jackknife (solver/jackknife.py), per data set.

For the sample, a simulated 30-frame dataset and each recording in ``../shared/real`` (imported
with ``calib3r-graph import``, the pairwise frontend's features and pair geometries cached under
``--cache``), on all poses and on ``--subsets`` seeded 10-pose subsets:

* both jackknives' per-axis sigmas and the covers of the total (``jackknife.cover`` of the
  modelled covariance and each jackknife's), as ratios linearised / re-solving;
* each left-out pose's shift of ee_T_cam by both (ee frame, deg and mm), side by side;
* ``--control``: the same with the robust re-weighting off (``irls_rounds=0``) in the solve and in
  every leave-one-out re-solve. The linearised jackknife holds the robust weights at the full
  solve's; where the two agree without re-weighting but not with it, the difference is the
  re-weighting's (docs/uncertainty.md, *Linearised jackknife*).
* the time of each;
* ``--repeat-seeds K``: both covers again with ``solve``'s own seeds 0..K-1, to show how finely the
  re-solving one, the reference, can judge the ratio.

    .venv/bin/python bench/jackknife.py [--data sample,sim,rwhe_kuka_1,rwhe_kuka_2,tabb_ds1] [--subsets 2]
        [--all-max 40] [--control] [--repeat-seeds K] [--work DIR] [--cache DIR] [--out bench/results]

Writes ``OUT/jackknife.json`` and ``OUT/jackknife.md``.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # see bench/views_real.py: set before numpy loads

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import gtsam  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from _workdirs import add_work_args, work_dirs  # noqa: E402  (bench/, the script's own folder)
from calib3r_graph.io.dataset import load_dataset, subset_dataset  # noqa: E402
from calib3r_graph.io.predictions import load_predictions, subset_predictions  # noqa: E402
from calib3r_graph.solver import jackknife as jk  # noqa: E402
from calib3r_graph.solver.graph import NoiseOptions  # noqa: E402
from calib3r_graph.solver.solve import SolveOptions, solve  # noqa: E402

SHARED = ROOT.parent / "shared" / "real"
BOARDS = {"rwhe_kuka_1": (28, 17), "rwhe_kuka_2": (24, 17)}  # inner corners, as bench/live_real.py
SUBSET_POSES = 10


def prepare(name, work: Path, cache: Path):
    """(Dataset, Predictions) of a data set name."""
    if name == "sample":
        ds = load_dataset(ROOT / "datasets" / "sample")
        return ds, load_predictions(ds.root, "sim", ds.cameras, set(ds.frames))
    ds_dir = work / name
    if name == "sim":
        if not (ds_dir / "dataset.yaml").exists():
            from calib3r_graph.simulate import SimOptions, simulate

            simulate(ds_dir, SimOptions(seed=11, frames=30, cameras=1, images=False, matches_per_pair=500), progress=False)
        ds = load_dataset(ds_dir)
        return ds, load_predictions(ds_dir, "sim", ds.cameras, set(ds.frames))
    from calib3r_graph.frontends.pairwise import pairwise_predictions

    if not (ds_dir / "dataset.yaml").exists():
        from calib3r_graph.importers import import_recording

        src = SHARED / name
        import_recording("tabb" if (src / "robot_cali.txt").exists() else "rwhe", src, ds_dir, BOARDS.get(name),
                         progress=False)
    ds = load_dataset(ds_dir)
    return ds, pairwise_predictions(ds, None, cache_dir=cache / name, progress=False)


def _ee(X, d):
    """A tangent step (rad, m; GTSAM order) of ee_T_cam in the ee frame: (deg x3, mm x3)."""
    R = X.rotation().matrix()
    return np.r_[np.degrees(R @ d[:3]), 1e3 * (R @ d[3:])]


def compare(ds, preds, frames, irls_rounds):
    """Rows (one per camera) comparing the two jackknives on ``frames`` at ``irls_rounds``."""
    sub, sp = subset_dataset(ds, frames), subset_predictions(preds, frames)
    opt = SolveOptions(noise=NoiseOptions(pixel_sigma_px=float(preds.info.get("match_noise_px", 1.0))), progress=False,
                       irls_rounds=irls_rounds, jackknife="never")
    t = time.perf_counter()
    sol = solve(sub, sp, opt)
    t_solve = time.perf_counter() - t
    t = time.perf_counter()
    lin, lin_pose = jk.linearised_jackknife(sol)
    t_lin = time.perf_counter() - t
    shifts_lin, _, _ = jk.linearised_leave_one_out(sol.graph, sol.values, sol.keys, list(sol.base_T_cam))
    # the re-solving one, with its leave-one-out solutions kept for the side-by-side shifts (in one
    # process, so that its time is the work's, as the linearised one's)
    used = sol.frames
    t = time.perf_counter()
    logging.getLogger("calib3r_graph").setLevel(logging.ERROR)
    solves = jk.leave_one_out_solves(sub, sp, dataclasses.replace(opt, jackknife="never", jobs=1), used, solve, False)
    shifts_res = {f: X for f, (X, _) in solves.items()}
    fits = {f: fit for f, (_, fit) in solves.items() if fit}
    res = jk._jackknife_report(sol, {c: [X[c] for X in shifts_res.values() if c in X] for c in sol.ee_T_cam})
    t_res = time.perf_counter() - t
    rows = []
    for c in sol.ee_T_cam:
        if c not in lin or c not in res:
            rows.append({"frames": list(frames), "camera": c, "irls_rounds": irls_rounds,
                         "error": f"too few leave-one-out samples (linearised {c in lin}, re-solving {c in res})"})
            continue
        X, C = sol.ee_T_cam[c], np.asarray(sol.covariance[c])
        a, b = lin[c]["sigma_jackknife"], res[c]["sigma_jackknife"]
        ca = jk._sigmas(X, jk.cover(C, np.asarray(lin[c]["covariance"])))
        cb = jk._sigmas(X, jk.cover(C, np.asarray(res[c]["covariance"])))
        per_pose = {f: {"linearised": _ee(X, shifts_lin[f][c]).tolist() if f in shifts_lin else None,
                        "resolve": _ee(X, gtsam.Pose3.Logmap(X.between(shifts_res[f][c]))).tolist()
                        if c in shifts_res.get(f, {}) else None} for f in used}
        rows.append({"frames": list(frames), "camera": c, "irls_rounds": irls_rounds, "poses": len(used),
                     "samples": [lin[c]["solves"], res[c]["solves"]], "time_solve_s": t_solve,
                     "time_linearised_s": t_lin, "time_resolve_s": t_res,
                     "sigma_model_total": jk._sigmas(X, C), "sigma_linearised": a, "sigma_resolve": b,
                     "sigma_ratio": {k: a[k] / b[k] for k in a}, "cover_ratio": {k: ca[k] / cb[k] for k in ca},
                     "influential_pose": [lin_pose and lin_pose["frame"], jk.influential_pose(
                         sol.stats["noise_calibration"].get("robot_chi2_dof"), fits) and
                         jk.influential_pose(sol.stats["noise_calibration"].get("robot_chi2_dof"), fits)["frame"]],
                     "per_pose_shift_ee": per_pose})
    return rows


def repeatability(ds, preds, frames, seeds: int) -> list:
    """Rows (one per camera): how much each jackknife's cover of the total moves with ``solve``'s
    own arbitrary draws (``SolveOptions.seed``: the match subsample, the pairwise RANSAC and the
    closed-form start), seeds 0 to ``seeds`` - 1 on ``frames``: max / min per ee axis over the seeds,
    and the spread (standard deviation) of the result itself. A reference that moves this much
    cannot judge a ratio more finely."""
    sub, sp = subset_dataset(ds, frames), subset_predictions(preds, frames)
    covers, results = {}, {}
    for seed in range(seeds):
        opt = SolveOptions(noise=NoiseOptions(pixel_sigma_px=float(preds.info.get("match_noise_px", 1.0))),
                           progress=False, jackknife="never", seed=seed)
        sol = solve(sub, sp, opt)
        lin, _ = jk.linearised_jackknife(sol)
        res, _ = jk.jackknife(sub, sp, dataclasses.replace(opt, jackknife_method="resolve"), sol, solve, progress=False)
        for c, X in sol.ee_T_cam.items():
            if c not in lin or c not in res:
                continue
            C = np.asarray(sol.covariance[c])
            covers.setdefault(c, []).append([list(jk._sigmas(X, jk.cover(C, np.asarray(r[c]["covariance"]))).values())
                                             for r in (lin, res)])
            results.setdefault(c, []).append(X)
    rows = []
    for c, cv in covers.items():
        cv = np.array(cv)  # (seeds, 2, 6)
        X0 = results[c][0]
        spread = np.std([_ee(X0, gtsam.Pose3.Logmap(X0.between(X))) for X in results[c]], axis=0)
        rows.append({"frames": list(frames), "camera": c, "seeds": len(cv),
                     "linearised_max_over_min": (cv[:, 0].max(0) / cv[:, 0].min(0)).tolist(),
                     "resolve_max_over_min": (cv[:, 1].max(0) / cv[:, 1].min(0)).tolist(),
                     "ratio_range": [float((cv[:, 0] / cv[:, 1]).min()), float((cv[:, 0] / cv[:, 1]).max())],
                     "result_spread_ee": spread.tolist()})
    return rows


def coverage(ds, preds, poses, subsets, seed=0):
    """On ``subsets`` seeded subsets of ``poses`` poses: the largest |error / total sigma| over the
    six ee axes against the full data set's result, with the linearised jackknife, the re-solving
    one and none. Rows per subset and camera."""
    from calib3r_graph.evaluation.compare import random_subsets
    from calib3r_graph.io.results import covariance_in_ee_frame

    base = SolveOptions(noise=NoiseOptions(pixel_sigma_px=float(preds.info.get("match_noise_px", 1.0))), progress=False,
                        jobs=1)  # (one process: the times compare the two methods' work)
    ref = solve(ds, preds, dataclasses.replace(base, jackknife="never"))
    rows = []
    for frames in random_subsets(ds, poses, subsets, seed):
        sub, sp = subset_dataset(ds, frames), subset_predictions(preds, frames)
        row = {"frames": frames}
        for label, opt in (("linearised", dataclasses.replace(base, jackknife="always", jackknife_method="linearised")),
                           ("resolve", dataclasses.replace(base, jackknife="always", jackknife_method="resolve"))):
            t = time.perf_counter()
            try:
                sol = solve(sub, sp, opt)
            except Exception as e:  # noqa: BLE001  a subset that does not solve is counted apart
                row[label] = {"error": f"{type(e).__name__}: {e}"}
                continue
            z = {}
            for c, X in sol.ee_T_cam.items():
                d = gtsam.Pose3.Logmap(ref.ee_T_cam[c].between(X))
                R = X.rotation().matrix()
                e = np.abs(np.r_[R @ d[:3], R @ d[3:]])
                before = np.asarray(sol.stats.get("jackknife", {}).get(c, {}).get("covariance_before", sol.covariance[c]))
                z[c] = {"total": float(np.max(e / np.sqrt(np.diag(covariance_in_ee_frame(X, sol.covariance[c]))))),
                        "without_jackknife": float(np.max(e / np.sqrt(np.diag(covariance_in_ee_frame(X, before)))))}
            row[label] = {"max_abs_z": z, "time_s": time.perf_counter() - t}
        rows.append(row)
        print(poses, frames, {k: v for k, v in row.items() if k != "frames"}, flush=True)
    return rows


def coverage_summary(rows) -> dict:
    out = {}
    for label in ("linearised", "resolve"):
        ok = [r[label]["max_abs_z"] for r in rows if "max_abs_z" in r.get(label, {})]
        zs = [z for d in ok for z in d.values()]
        out[label] = {"subsets": len(ok), "within_3sigma": float(np.mean([z["total"] <= 3 for z in zs])) if zs else None,
                      "within_3sigma_without_jackknife":
                          float(np.mean([z["without_jackknife"] <= 3 for z in zs])) if zs else None,
                      "time_median_s": float(np.median([r[label]["time_s"] for r in rows if "time_s" in r.get(label, {})]))
                      if ok else None}
    return out


def picks_of(ds, subsets, all_max, consecutive=False, seed=0):
    """All poses (up to ``all_max``) and ``subsets`` 10-pose subsets: seeded random ones, or runs of
    consecutive frames at evenly spaced starts (``consecutive``: on tabb_ds1's 88 frames random
    10-pose subsets share too few views to solve)."""
    from calib3r_graph.evaluation.compare import random_subsets

    picks = []
    if len(ds.frames) <= all_max:
        picks.append(list(ds.frames))
    if len(ds.frames) > SUBSET_POSES:
        if consecutive:
            starts = np.linspace(0, len(ds.frames) - SUBSET_POSES, subsets).astype(int)
            picks += [list(ds.frames[i:i + SUBSET_POSES]) for i in starts]
        else:
            picks += random_subsets(ds, SUBSET_POSES, subsets, seed)
    return picks


def table(result) -> str:
    lines = [f"Command: `{result['command']}`", "",
             "Linearised / re-solving jackknife: min–max over the six ee axes of the ratio of the jackknife sigmas and "
             "of the covers of the total (what `solve` reports); samples = leave-one-out solutions used "
             "(linearised, re-solving); IRLS = robust re-weighting rounds (2: `solve`'s default; 0: the control "
             "without re-weighting).", "",
             "| data | poses | IRLS | samples | jackknife σ ratio | cover ratio | time solve / linearised / re-solving (s) |",
             "|---|---|---|---|---|---|---|"]
    for name, rows in result["data"].items():
        for r in rows:
            if "error" in r:
                lines.append(f"| {name} {r.get('camera', '')} | {len(r['frames'])} | {r.get('irls_rounds', '')} | "
                             f"{r['error']} | | | |")
                continue
            s, c = list(r["sigma_ratio"].values()), list(r["cover_ratio"].values())
            lines.append(f"| {name} {r['camera']} | {r['poses']} | {r['irls_rounds']} | {r['samples'][0]}, "
                         f"{r['samples'][1]} | {min(s):.2f}–{max(s):.2f} | {min(c):.2f}–{max(c):.2f} | "
                         f"{r['time_solve_s']:.1f} / {r['time_linearised_s']:.2f} / {r['time_resolve_s']:.1f} |")
    if result.get("repeatability"):
        lines += ["", "How much the covers move with `solve`'s own seeds (`--repeat-seeds K`: the match subsample, the "
                  "pairwise RANSAC and the closed-form start seeded 0 to K - 1): max / min over the seeds of each "
                  "method's cover of the total, the largest over the six ee axes; the cover ratio linearised / "
                  "re-solving over all seeds and axes; the result's own spread (standard deviation, largest axis).",
                  "", "| data | poses | seeds | re-solving cover max / min | linearised cover max / min | "
                  "cover ratio, all seeds | result spread (deg, mm) |", "|---|---|---|---|---|---|---|"]
        for name, rows in result["repeatability"].items():
            for r in rows:
                sp = r["result_spread_ee"]
                lines.append(f"| {name} {r['camera']} | {len(r['frames'])} | {r['seeds']} | "
                             f"{max(r['resolve_max_over_min']):.2f} | {max(r['linearised_max_over_min']):.2f} | "
                             f"{r['ratio_range'][0]:.2f}–{r['ratio_range'][1]:.2f} | {max(sp[:3]):.3f}, {max(sp[3:]):.3f} |")
    if result.get("coverage"):
        lines += ["", "Share of seeded subsets (x cameras) whose ee_T_cam is within 3 total sigma of the full data set's "
                  "on every ee axis, with each jackknife (and with the modelled covariance alone):", "",
                  "| data | poses | subsets | linearised | re-solving | no jackknife | solve time, linearised / "
                  "re-solving (s, median) |", "|---|---|---|---|---|---|---|"]
        for name, by_n in result["coverage"].items():
            for k, v in by_n.items():
                a, b = v["summary"]["linearised"], v["summary"]["resolve"]
                pct = lambda x: "–" if x is None else f"{x:.0%}"  # noqa: E731
                lines.append(f"| {name} | {k} | {a['subsets']}, {b['subsets']} | {pct(a['within_3sigma'])} | "
                             f"{pct(b['within_3sigma'])} | {pct(a['within_3sigma_without_jackknife'])} | "
                             f"{a['time_median_s'] or 0:.1f} / {b['time_median_s'] or 0:.1f} |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="sample,sim,rwhe_kuka_1,rwhe_kuka_2,tabb_ds1")
    ap.add_argument("--subsets", type=int, default=2, help="seeded 10-pose subsets per data set")
    ap.add_argument("--all-max", type=int, default=40, help="also all poses, up to this many")
    ap.add_argument("--control", action="store_true", help="also with the robust re-weighting off (irls_rounds=0)")
    ap.add_argument("--coverage", default="", help="pose counts (e.g. 6,8): 3-sigma coverage of the full result "
                    "on seeded subsets, with each jackknife")
    ap.add_argument("--coverage-subsets", type=int, default=20)
    ap.add_argument("--no-compare", action="store_true", help="only --coverage (and --repeat-seeds)")
    ap.add_argument("--repeat-seeds", type=int, default=0,
                    help="also re-run both jackknives on each pick with solve's seeds 0..K-1 (the reference's repeatability)")
    ap.add_argument("--consecutive", default="tabb_ds1",
                    help="data sets whose 10-pose subsets are runs of consecutive frames (default: tabb_ds1)")
    add_work_args(ap, "jackknife_bench")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR, format="%(levelname)s: %(message)s")
    work, cache, out = work_dirs(args)
    result = {"command": " ".join(sys.argv), "data": {}}
    default_rounds = SolveOptions().irls_rounds
    for name in args.data.split(","):
        if name not in ("sample", "sim") and not (SHARED / name).is_dir():
            print(f"{name}: not in {SHARED}, skipped", file=sys.stderr)
            continue
        ds, preds = prepare(name, work, cache)
        rows = []
        if args.coverage:
            cov = {int(k): coverage(ds, preds, int(k), args.coverage_subsets) for k in args.coverage.split(",")}
            result.setdefault("coverage", {})[name] = {k: {"summary": coverage_summary(v), "rows": v} for k, v in cov.items()}
        if args.repeat_seeds:
            result.setdefault("repeatability", {})[name] = [
                r for frames in picks_of(ds, args.subsets, args.all_max, name in args.consecutive.split(","))
                for r in repeatability(ds, preds, frames, args.repeat_seeds)]
        for frames in [] if args.no_compare else picks_of(ds, args.subsets, args.all_max, name in args.consecutive.split(",")):
            for rounds in (default_rounds, 0) if args.control else (default_rounds,):
                try:
                    rows += compare(ds, preds, frames, rounds)
                except Exception as e:  # noqa: BLE001  a subset that does not solve is reported, not fatal
                    rows.append({"frames": list(frames), "irls_rounds": rounds, "error": f"{type(e).__name__}: {e}"})
                print(table({"command": "", "data": {name: rows[-1:]}}).splitlines()[-1], flush=True)
        if rows:
            result["data"][name] = rows
        (out / "jackknife.json").write_text(json.dumps(result, indent=1, default=float))
    (out / "jackknife.json").write_text(json.dumps(result, indent=1, default=float))
    (out / "jackknife.md").write_text(table(result))
    print(table(result))


if __name__ == "__main__":
    main()
