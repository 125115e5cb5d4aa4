"""Does the guide predict what one more pose does? Its predicted total sigma after a candidate
against the total sigma that solving with that pose then reports, on the real recordings.

For each recording (prepared as ``bench/live_real.py`` prepares it: the pairwise frontend from a
pair cache, or the simulator's predictions) and each seeded random order, at n frames of it: solve
the first n frames (``solve``, the linearised jackknife, as a live update's cover), score every
unused recorded frame with the guide (``guidance.score_candidates``, what ``live --replay guided``
and ``plan --candidates`` run), then solve the n + 1 frames with each candidate added and read
its reported total sigma. The predictions are the full recording's, restricted to the frames
used, on both sides. Reported per recording and n:

- the ratio predicted / solved of the largest total sigma (translation mm, rotation deg; median and
  10-90 % range over candidates): 1 is a guide that predicts the sigma a pose brings;
- Spearman's rank correlation between the predicted and the solved objective (the stop rule's
  quantity, ``guidance.objective``) over the candidates: whether the guide ranks them right;
- the regret of its pick: the solved objective of the candidate it ranks first, over the best
  solved one (1 = it picked the best), and the best's rank in the guide's order.

    .venv/bin/python bench/guide_prediction.py [--recordings rwhe_kuka_1,rwhe_kuka_2,tabb_ds1,sim]
        [--frames 6,10,15] [--seeds 3] [--max-candidates 15] [--work /tmp/live_real --cache /tmp/live_real/cache] [--out DIR]

Writes ``OUT/guide_prediction.json`` and ``OUT/guide_prediction.md``.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # see bench/views_real.py: set before numpy loads

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _workdirs import add_work_args, work_dirs  # noqa: E402  (bench/, the script's own folder)
from live_real import SHARED, prepare  # noqa: E402
from calib3r_graph.errors import Calib3rError  # noqa: E402
from calib3r_graph.io.dataset import load_dataset, subset_dataset  # noqa: E402
from calib3r_graph.io.predictions import subset_predictions  # noqa: E402
from calib3r_graph.io.results import largest_sigma, uncertainty_report  # noqa: E402
from calib3r_graph.solver.graph import NoiseOptions  # noqa: E402
from calib3r_graph.solver.guidance import objective, scene_geometry, score_candidates  # noqa: E402
from calib3r_graph.solver.solve import SolveOptions, solve  # noqa: E402

TARGET = (1.0, 0.1)  # mm, deg: the live default, which scales the objective's axes


def solved(ds, preds, frames, opt):
    """solve on ``frames``, or None where it does not solve."""
    try:
        return solve(subset_dataset(ds, frames), subset_predictions(preds, frames), opt)
    except Calib3rError:
        return None


def one_point(ds, preds, opt, frames, rest) -> dict | None:
    """The guide's predictions for every frame of ``rest`` after ``frames``, and the solves with each."""
    sol = solved(ds, preds, frames, opt)
    if sol is None:
        return None
    robot_mm, robot_deg = sol.stats["noise_calibration"]["robot_sigma_used"]
    noise = dataclasses.replace(opt.noise, robot_sigma_mm=robot_mm, robot_sigma_deg=robot_deg)
    sub = subset_dataset(ds, frames)
    t = time.perf_counter()
    ranked = score_candidates(sol, subset_predictions(preds, frames), noise, sub.base_T_ee,
                              [("recorded", ds.base_T_ee[f], f) for f in rest], *TARGET)
    score_s = time.perf_counter() - t
    d_med = float(np.median(scene_geometry(sol)[1]))
    now = largest_sigma({c: uncertainty_report(X, sol.covariance[c])["sigma_ee_frame"] for c, X in sol.ee_T_cam.items()})
    rows = []
    for rank, p in enumerate(ranked, 1):
        after = solved(ds, preds, frames + [p.frame], opt)
        if after is None:
            continue
        sig = {c: uncertainty_report(X, after.covariance[c])["sigma_ee_frame"] for c, X in after.ee_T_cam.items()}
        J = objective(after.covariance, after.ee_T_cam, {c: after.metric_scale[c][1] / abs(after.metric_scale[c][0])
                                                         for c in after.ee_T_cam}, d_med, *TARGET)
        rows.append({"frame": p.frame, "rank": rank, "predicted_objective": p.objective_after, "solved_objective": J,
                     "predicted_mm_deg": list(largest_sigma(p.sigma_after)), "solved_mm_deg": list(largest_sigma(sig)),
                     "visible_points": p.visible_points})
    return {"frames": list(frames), "now_mm_deg": list(now), "score_s": score_s, "candidates": rows}


def spearman(a, b) -> float:
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1]) if len(a) > 2 else float("nan")


def summary(points) -> dict:
    ratio_mm = [r["predicted_mm_deg"][0] / r["solved_mm_deg"][0] for p in points for r in p["candidates"]]
    ratio_deg = [r["predicted_mm_deg"][1] / r["solved_mm_deg"][1] for p in points for r in p["candidates"]]
    rho, regret, regret_random, best_rank, spread = [], [], [], [], []
    for p in points:
        c = p["candidates"]
        if len(c) < 3:
            continue
        pred, sol = [r["predicted_objective"] for r in c], [r["solved_objective"] for r in c]
        rho.append(spearman(pred, sol))
        first = min(c, key=lambda r: r["rank"])
        regret.append(first["solved_objective"] / min(sol))
        regret_random.append(float(np.mean(sol)) / min(sol))  # a pick at random, on average
        spread.append(max(sol) / min(sol))
        best_rank.append(sorted(r["rank"] for r in c).index(min(c, key=lambda r: r["solved_objective"])["rank"]) + 1)
    pct = lambda x, q: float(np.percentile(x, q)) if x else float("nan")  # noqa: E731
    return {"points": len(points), "candidates": len(ratio_mm),
            "ratio_mm": [pct(ratio_mm, 10), pct(ratio_mm, 50), pct(ratio_mm, 90)],
            "ratio_deg": [pct(ratio_deg, 10), pct(ratio_deg, 50), pct(ratio_deg, 90)],
            "spearman": [pct(rho, 0), pct(rho, 50), pct(rho, 100)],
            "regret": [pct(regret, 50), pct(regret, 100)], "regret_random": [pct(regret_random, 50)],
            "objective_spread": [pct(spread, 50)],
            "best_rank": [pct(best_rank, 50), pct(best_rank, 100)],
            "candidates_per_point": len(ratio_mm) / max(len(points), 1)}


def table(result) -> str:
    lines = [f"Command: `{result['command']}`", "",
             "Predicted / solved largest total sigma after one more pose (10 / 50 / 90 % over the candidates); "
             "Spearman's rho between the predicted and the solved objective per point (min / median / max); "
             "the solved objective of the guide's pick over the best candidate's (median / max), beside a "
             "random pick's (the candidates' mean over the best, median over the points) and the candidates' "
             "own spread (worst over best, median); the best candidate's rank in the guide's order (median / max).",
             "",
             "| recording | frames | points | candidates | translation ratio | rotation ratio | rho | regret: guide | "
             "random | spread | best's rank |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    f3 = lambda x: " / ".join(f"{v:.2f}" for v in x)  # noqa: E731
    for name, by_n in result["recordings"].items():
        for n, rec in by_n.items():
            s = rec["summary"]
            lines.append(f"| {name} | {n} | {s['points']} | {s['candidates']} | {f3(s['ratio_mm'])} | "
                         f"{f3(s['ratio_deg'])} | {f3(s['spearman'])} | {f3(s['regret'])} | {f3(s['regret_random'])} | "
                         f"{f3(s['objective_spread'])} | "
                         f"{' / '.join(f'{v:.0f}' for v in s['best_rank'])} |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", default="rwhe_kuka_1,rwhe_kuka_2,tabb_ds1,sim")
    ap.add_argument("--frames", default="6,10,15", help="frame counts at which the guide is asked")
    ap.add_argument("--seeds", type=int, default=3,
                    help="random orders per recording and frame count that solve (up to 4x as many tried)")
    ap.add_argument("--max-candidates", type=int, default=15,
                    help="at most this many unused frames a point (seeded draw; tabb_ds1 has 88)")
    add_work_args(ap, "live_real")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR, format="%(levelname)s: %(message)s")
    work, cache, out = work_dirs(args)
    result = {"command": " ".join(sys.argv), "recordings": {}}
    for name in args.recordings.split(","):
        if name != "sim" and not (SHARED / name).is_dir():
            print(f"{name}: not in {SHARED}, skipped")
            continue
        ds_dir, _, preds, _, _ = prepare(name, work, cache)
        ds = load_dataset(ds_dir)
        opt = SolveOptions(noise=NoiseOptions(pixel_sigma_px=float(preds.info.get("match_noise_px", 1.0))),
                           jackknife_method="linearised", progress=False)
        by_n = {}
        for n in (int(x) for x in args.frames.split(",")):
            points = []
            for seed in range(4 * args.seeds):
                if len(points) == args.seeds:
                    break
                rng = np.random.default_rng(seed)
                order = [str(f) for f in rng.permutation(ds.frames)]
                rest = order[n:]
                if len(rest) > args.max_candidates:
                    rest = [str(f) for f in rng.choice(rest, args.max_candidates, replace=False)]
                t = time.perf_counter()
                p = one_point(ds, preds, opt, order[:n], rest)
                if p is None:
                    print(f"  {name} n={n} seed {seed}: does not solve", flush=True)
                    continue
                p["seed"] = seed
                points.append(p)
                print(f"  {name} n={n} seed {seed}: {len(p['candidates'])} candidates, {time.perf_counter() - t:.0f} s",
                      flush=True)
            by_n[str(n)] = {"summary": summary(points), "points": points}
        result["recordings"][name] = by_n
        (out / "guide_prediction.json").write_text(json.dumps(result, indent=1, default=float))
    (out / "guide_prediction.md").write_text(table(result))
    print(table(result))


if __name__ == "__main__":
    main()
