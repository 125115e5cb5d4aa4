"""Live calibration on the real recordings and the simulator: recorded, guided and random orders.

For each recording (``../shared/real``: imported with ``calib3r-graph import``, the pairwise
frontend run frame by frame with its features and pair geometries cached under ``--cache``) and a
simulated dataset (its own predictions), the recording is replayed through ``LiveSession``:

* per step: the error of ee_T_cam to the full recording's batch ``solve`` (mm, deg), the largest
  total sigma (mm, deg), and whether the error is within 3 sigma on every ee axis (coverage);
* the frames each order needs to come within 3 mm / 0.2 deg of the full result and stay there;
* the latency of each update (the solver's part; the frontend's feature extraction, pair geometry
  and aggregation and the guidance's scoring reported apart) and all updates against one batch solve;
* the final live result against batch solve, in sigma per ee axis (the equivalence goal).

``--jackknife`` also compares the linearised leave-one-pose-out jackknife (solver/jackknife.py) with
the re-solving one on ``--jk-subsets`` seeded 10-pose subsets of each recording and on the sample.

    .venv/bin/python bench/live_real.py [--recordings rwhe_kuka_1,rwhe_kuka_2,tabb_ds1,sim] [--seeds 20]
        [--jackknife] [--work DIR] [--cache DIR] [--out bench/results]

Writes ``OUT/live_real.json``, ``OUT/live_real.md`` and ``OUT/live_real_<recording>.png``.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # see bench/views_real.py: set before numpy loads

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import gtsam  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from calib3r_graph.geometry import pose_error  # noqa: E402
from calib3r_graph.io.dataset import load_dataset, subset_dataset  # noqa: E402
from calib3r_graph.io.predictions import load_predictions, subset_predictions  # noqa: E402
from calib3r_graph.io.results import covariance_in_ee_frame  # noqa: E402
from calib3r_graph.live.run import replay  # noqa: E402
from calib3r_graph.live.session import LiveSession  # noqa: E402
from calib3r_graph.solver import jackknife as jk  # noqa: E402
from calib3r_graph.solver.graph import NoiseOptions  # noqa: E402
from calib3r_graph.solver.solve import SolveOptions, solve  # noqa: E402

log = logging.getLogger("live_real")
SHARED = ROOT.parent / "shared" / "real"
BOARDS = {"rwhe_kuka_1": (28, 17), "rwhe_kuka_2": (24, 17)}
NEAR_MM, NEAR_DEG = 3.0, 0.2


def prepare(name, work: Path, cache: Path):
    """(dataset dir, predictions name or None, batch predictions, reference Solution, batch solve s)."""
    from calib3r_graph.frontends.pairwise import pairwise_predictions

    ds_dir = work / name
    if name == "sim":
        if not (ds_dir / "dataset.yaml").exists():
            from calib3r_graph.simulate import SimOptions, simulate

            simulate(ds_dir, SimOptions(seed=11, frames=30, cameras=1, images=False, matches_per_pair=500), progress=False)
        ds = load_dataset(ds_dir)
        preds, pname = load_predictions(ds_dir, "sim", ds.cameras, set(ds.frames)), "sim"
    else:
        if not (ds_dir / "dataset.yaml").exists():
            from calib3r_graph.importers import import_recording

            src = SHARED / name
            import_recording("tabb" if (src / "robot_cali.txt").exists() else "rwhe", src, ds_dir, BOARDS.get(name),
                             progress=False)
        ds = load_dataset(ds_dir)
        preds, pname = pairwise_predictions(ds, None, cache_dir=cache / name, progress=False), None
    opt = SolveOptions(noise=NoiseOptions(pixel_sigma_px=float(preds.info.get("match_noise_px", 1.0))), progress=False)
    t = time.perf_counter()
    ref = solve(ds, preds, opt)
    return ds_dir, pname, preds, ref, time.perf_counter() - t


def run_order(ds_dir, pname, cache, ref, order, seed):
    session = LiveSession(ds_dir, predictions=pname, cache_dir=cache, guide=False, seed=seed)
    steps = []

    def record(up):
        row = {"frames": len(up.frames), "latency_s": up.latency_s, "frontend_s": up.frontend_s,
               "message": up.message}
        if up.ee_T_cam:
            cams = {}
            for c, T in up.ee_T_cam.items():
                X = gtsam.Pose3(np.array(T))
                t_err, r_err = pose_error(X, ref.ee_T_cam[c])
                d = gtsam.Pose3.Logmap(ref.ee_T_cam[c].between(X))
                R = X.rotation().matrix()
                e = np.abs(np.r_[np.degrees(R @ d[:3]), 1e3 * (R @ d[3:])])
                s = up.sigma_ee_frame[c]
                sig = np.array([s["rx_deg"], s["ry_deg"], s["rz_deg"], s["x_mm"], s["y_mm"], s["z_mm"]])
                cams[c] = {"error_mm": 1e3 * t_err, "error_deg": r_err, "sigma_mm": float(sig[3:].max()),
                           "sigma_deg": float(sig[:3].max()), "covered": bool(np.all(e <= 3 * sig))}
            row["cameras"] = cams
        steps.append(row)

    t = time.perf_counter()
    ups = replay(session, order, seed, on_update=record)
    wall = time.perf_counter() - t
    final = {}
    if session.sol is not None:
        for c, X in session.sol.ee_T_cam.items():
            d = gtsam.Pose3.Logmap(ref.ee_T_cam[c].between(X))
            R = X.rotation().matrix()
            z = np.r_[R @ d[:3], R @ d[3:]] / np.sqrt(np.diag(covariance_in_ee_frame(X, ref.covariance[c])))
            final[c] = z.tolist()
    return {"order": order, "seed": seed, "steps": steps, "wall_s": wall, "final_z": final,
            "frames_order": list(session.base_T_ee)}  # arrival order


def frames_to_stay_near(steps) -> int | None:
    """Fewest frames after which every later update is within 3 mm / 0.2 deg of the full result."""
    ok = [("cameras" in s and all(c["error_mm"] <= NEAR_MM and c["error_deg"] <= NEAR_DEG
                                  for c in s["cameras"].values())) for s in steps[:-1]]  # the last: finish()
    for i in range(len(ok)):
        if all(ok[i:]):
            return steps[i]["frames"]
    return None


def summarise(runs, batch_s):
    out = {}
    for order in ("recorded", "guided", "random"):
        rs = [r for r in runs if r["order"] == order]
        if not rs:
            continue
        need = [frames_to_stay_near(r["steps"]) for r in rs]
        cov = [c["covered"] for r in rs for s in r["steps"][:-1] for c in s.get("cameras", {}).values()]
        lat = [s["latency_s"] for r in rs for s in r["steps"][:-1] if "cameras" in s]
        total = [sum(s["latency_s"] for s in r["steps"]) for r in rs]
        front = [sum(sum(s["frontend_s"].values()) for s in r["steps"]) for r in rs]
        z = [max(abs(v) for c in r["final_z"].values() for v in c) for r in rs if r["final_z"]]
        out[order] = {"runs": len(rs), "frames_to_3mm_0.2deg": need,
                      "frames_median": float(np.median([n for n in need if n is not None])) if any(
                          n is not None for n in need) else None,
                      "coverage_3sigma": float(np.mean(cov)) if cov else None,
                      "latency_median_s": float(np.median(lat)) if lat else None,
                      "latency_at_max_frames_s": float(np.median([r["steps"][-2]["latency_s"] for r in rs])),
                      "updates_total_s": float(np.median(total)), "frontend_total_s": float(np.median(front)),
                      "updates_over_batch": float(np.median(total) / batch_s), "final_max_abs_z": max(z) if z else None}
    return out


def compare_jackknife(ds_dir, pname, preds, subsets, seed=0):
    """Linearised vs re-solving jackknife sigmas and covers on seeded 10-pose subsets."""
    from calib3r_graph.evaluation.compare import random_subsets

    ds = load_dataset(ds_dir)
    opt = SolveOptions(noise=NoiseOptions(pixel_sigma_px=float(preds.info.get("match_noise_px", 1.0))), progress=False)
    rows = []
    picks = [ds.frames] if len(ds.frames) < jk.JACKKNIFE_BELOW else random_subsets(ds, 10, subsets, seed)
    for frames in picks:
        sub, sp = subset_dataset(ds, frames), subset_predictions(preds, frames)
        try:
            sol = solve(sub, sp, SolveOptions(**{**opt.__dict__, "jackknife": "never"}))
            t = time.perf_counter()
            lin, _ = jk.linearised_jackknife(sol)
            t_lin = time.perf_counter() - t
            jk.METHOD = "resolve"
            t = time.perf_counter()
            res, _ = jk.jackknife(sub, sp, opt, sol, solve, progress=False)
            t_res = time.perf_counter() - t
        except Exception as e:  # noqa: BLE001  a subset that does not solve is reported, not fatal
            rows.append({"frames": list(frames), "error": f"{type(e).__name__}: {e}"})
            continue
        finally:
            jk.METHOD = "linearised"
        for c in lin:
            if c not in res:
                continue
            a, b = lin[c]["sigma_jackknife"], res[c]["sigma_jackknife"]
            ca = jk._sigmas(sol.ee_T_cam[c], jk.cover(np.asarray(sol.covariance[c]), np.asarray(lin[c]["covariance"])))
            cb = jk._sigmas(sol.ee_T_cam[c], jk.cover(np.asarray(sol.covariance[c]), np.asarray(res[c]["covariance"])))
            rows.append({"frames": list(frames), "camera": c, "time_linearised_s": t_lin, "time_resolve_s": t_res,
                         "sigma_ratio": {k: a[k] / b[k] for k in a}, "cover_ratio": {k: ca[k] / cb[k] for k in ca}})
    return rows


def plot(name, runs, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    colours = {"recorded": "C0", "guided": "C3", "random": "C7"}
    for r in runs:
        xs = [s["frames"] for s in r["steps"][:-1] if "cameras" in s]
        if not xs:
            continue
        err = [max(c["error_mm"] for c in s["cameras"].values()) for s in r["steps"][:-1] if "cameras" in s]
        sig = [max(c["sigma_mm"] for c in s["cameras"].values()) for s in r["steps"][:-1] if "cameras" in s]
        kw = {"color": colours[r["order"]], "alpha": 0.35 if r["order"] == "random" else 1.0, "lw": 1}
        label = r["order"] if r["order"] != "random" or r["seed"] == 0 else None
        axes[0].semilogy(xs, err, label=label, **kw)
        axes[1].semilogy(xs, sig, label=label, **kw)
    for ax, what in zip(axes, ("error to the full batch result (mm)", "largest total sigma (mm)")):
        ax.set_xlabel("frames")
        ax.set_title(what)
        ax.axhline(NEAR_MM if "error" in what else 1.0, color="k", lw=0.5, ls="--")
        ax.legend()
    fig.suptitle(f"live replay: {name}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", default="rwhe_kuka_1,rwhe_kuka_2,tabb_ds1,sim")
    ap.add_argument("--seeds", type=int, default=20, help="random orders per recording")
    ap.add_argument("--orders", default="recorded,guided,random")
    ap.add_argument("--jackknife", action="store_true", help="also compare the two jackknives")
    ap.add_argument("--jk-subsets", type=int, default=3)
    ap.add_argument("--work", default="/tmp/live_real")
    ap.add_argument("--cache", default="/tmp/live_real/cache")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results"))
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s: %(message)s")
    work, cache, out = Path(args.work), Path(args.cache), Path(args.out)
    work.mkdir(parents=True, exist_ok=True)
    result = {"command": " ".join(sys.argv), "recordings": {}}
    for name in args.recordings.split(","):
        if name != "sim" and not (SHARED / name).is_dir():
            print(f"{name}: not in {SHARED}, skipped")
            continue
        t = time.perf_counter()
        ds_dir, pname, preds, ref, batch_s = prepare(name, work, cache)
        print(f"{name}: batch solve {batch_s:.1f} s (prepared in {time.perf_counter() - t:.0f} s)", flush=True)
        runs = []
        orders = (("recorded", [0]), ("guided", [0]), ("random", range(args.seeds)))
        for order, seeds in [(o, s) for o, s in orders if o in args.orders.split(",")]:
            for seed in seeds:
                r = run_order(ds_dir, pname, cache / name, ref, order, seed)
                runs.append(r)
                print(f"  {order} {seed}: to 3 mm / 0.2 deg after {frames_to_stay_near(r['steps'])} frames, "
                      f"updates {sum(s['latency_s'] for s in r['steps']):.1f} s, final |z| "
                      f"{max((abs(v) for c in r['final_z'].values() for v in c), default=float('nan')):.3f}",
                      flush=True)
        rec = {"batch_solve_s": batch_s, "frames": len(load_dataset(ds_dir).frames), "summary": summarise(runs, batch_s),
               "runs": runs}
        if args.jackknife:
            rec["jackknife"] = compare_jackknife(ds_dir, pname, preds, args.jk_subsets)
        result["recordings"][name] = rec
        plot(name, runs, out / f"live_real_{name}.png")
        (out / "live_real.json").write_text(json.dumps(result, indent=1, default=float))
    if args.jackknife:
        ds = load_dataset(ROOT / "datasets" / "sample")
        sp = load_predictions(ds.root, "sim", ds.cameras, set(ds.frames))
        result["sample_jackknife"] = compare_jackknife(ds.root, "sim", sp, 1)
    (out / "live_real.json").write_text(json.dumps(result, indent=1, default=float))
    (out / "live_real.md").write_text(table(result))
    print(table(result))


def table(result) -> str:
    lines = [f"Command: `{result['command']}`", "",
             "| recording | order | runs | frames to 3 mm / 0.2° (median) | 3σ coverage | median update (s) | "
             "update at all frames (s) | all updates / batch solve | frontend total (s) | final max \\|z\\| vs batch |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, rec in result["recordings"].items():
        for order, s in rec["summary"].items():
            fmt = lambda v, f: "–" if v is None else format(v, f)  # noqa: E731
            lines.append(f"| {name} ({rec['frames']} frames, batch {rec['batch_solve_s']:.1f} s) | {order} | {s['runs']} | "
                         f"{fmt(s['frames_median'], '.0f')} | {fmt(s['coverage_3sigma'], '.0%')} | "
                         f"{fmt(s['latency_median_s'], '.2f')} | {fmt(s['latency_at_max_frames_s'], '.2f')} | "
                         f"{fmt(s['updates_over_batch'], '.1f')}× | {fmt(s['frontend_total_s'], '.0f')} | "
                         f"{fmt(s['final_max_abs_z'], '.3f')} |")
    jrows = [(n, r) for n, rec in result["recordings"].items() for r in rec.get("jackknife", [])]
    jrows += [("sample", r) for r in result.get("sample_jackknife", [])]
    if jrows:
        lines += ["", "Linearised vs re-solving jackknife (ratio of per-axis sigmas; of the covers of the total):", "",
                  "| data | poses | jackknife σ ratio min–max | cover ratio min–max | time linearised / re-solving (s) |",
                  "|---|---|---|---|---|"]
        for n, r in jrows:
            if "error" in r:
                lines.append(f"| {n} | {len(r['frames'])} | {r['error']} | | |")
                continue
            s, c = list(r["sigma_ratio"].values()), list(r["cover_ratio"].values())
            lines.append(f"| {n} {r['camera']} | {len(r['frames'])} | {min(s):.2f}–{max(s):.2f} | {min(c):.2f}–{max(c):.2f} | "
                         f"{r['time_linearised_s']:.1f} / {r['time_resolve_s']:.1f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
