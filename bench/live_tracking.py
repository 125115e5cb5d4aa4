"""How closely the live engine follows ``solve``: each update against ``solve`` on the same frames
and the same predictions.

``bench/live_real.py`` measures each update against the *full* recording's result, which mixes two
things: how far the frames so far can take any solver, and how far the engine's one Gauss-Newton
step a frame falls from ``solve`` on those frames. This benchmark measures the second alone: at
every ``--every``-th update of a replay, ``solve`` runs on the frames so far with the predictions
the update used (the pairwise frontend's incremental ones, or a simulated dataset's), and the
update's ee_T_cam is compared with it in ``solve``'s own total sigma per ee axis.

    .venv/bin/python bench/live_tracking.py [--recordings rwhe_kuka_2] [--orders recorded,guided:0,random:3]
        [--every 1] [--extra-step-sigmas 1.5] [--work /tmp/live_real] [--cache /tmp/live_real/cache]
        [--tag NAME] [--batch-frontend]

``--orders``: ``recorded``, ``guided:SEED`` (the guided replay from ``live_real.py``'s start
``SEED``), ``random:SEED`` or ``file:PATH`` (a fixed order: frame ids, whitespace separated). Each
compared update and its ``solve`` are also compared with the full recording's result
(``update_to_full_mm_deg``, ``solve_to_full_mm_deg``): what the engine adds to the error of the frames
so far; with ``--batch-frontend`` also the batch pairwise frontend run on those frames alone, then
``solve`` (``batch_frontend_to_full_mm_deg``): what the incremental frontend adds. ``--extra-step-sigmas``: the engine's ``EXTRA_STEP_SIGMAS`` for this
run (0: no re-weighted second step), to measure it against the engine without it. Uses
``bench/live_real.py``'s prepared recordings. Writes ``OUT/live_tracking_<tag>.json`` and prints
one line per replay: the largest and the median |z| over the updates from 15 poses, the updates
beyond 1 sigma, the engine's extra steps and far-move re-runs, and the updates' CPU seconds.
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

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _workdirs import add_work_args, work_dirs  # noqa: E402
from live_real import ee_z, prepare  # noqa: E402
from calib3r_graph.geometry import pose_error  # noqa: E402
from calib3r_graph.live import engine as live_engine  # noqa: E402
from calib3r_graph.live.run import replay  # noqa: E402
from calib3r_graph.live.session import LiveSession  # noqa: E402
from calib3r_graph.solver.jackknife import JACKKNIFE_BELOW  # noqa: E402
from calib3r_graph.solver.solve import solve  # noqa: E402


def track(ds_dir, pname, cache, order, seed: int, every: int, full=None, batch_frontend=False) -> dict:
    """One replay with ``solve`` beside every ``every``-th update; ``order``: as ``replay`` takes it;
    ``full``: the full recording's result, to which both are also compared (mm, deg);
    ``batch_frontend``: also the batch pairwise frontend run on the frames so far alone, then ``solve``,
    against ``full`` (what a batch run on those frames gives)."""
    session = LiveSession(ds_dir, predictions=pname, cache_dir=cache, guide=False, seed=seed)
    engine, rows = session.engine, []
    update = engine.update

    def beside(base_T_ee, preds):
        c0 = time.process_time()
        sol = update(base_T_ee, preds)
        row = {"frames": len(base_T_ee), "cpu_s": time.process_time() - c0}
        if len(base_T_ee) % every == 0:
            sub = dataclasses.replace(engine.ds, base_T_ee=dict(base_T_ee))
            ref = solve(sub, preds, engine.opt)
            c = sorted(ref.ee_T_cam)[0]
            z = ee_z(sol.ee_T_cam[c], ref.ee_T_cam[c], ref.covariance[c])
            t, r = pose_error(sol.ee_T_cam[c], ref.ee_T_cam[c])
            row.update(z=z.tolist(), max_abs_z=float(np.abs(z).max()), mm=1e3 * t, deg=r)
            if full is not None:
                for who, X in (("update", sol.ee_T_cam[c]), ("solve", ref.ee_T_cam[c])):
                    t, r = pose_error(X, full.ee_T_cam[c])
                    row[f"{who}_to_full_mm_deg"] = [1e3 * t, r]
            if full is not None and batch_frontend and pname is None:
                from calib3r_graph.frontends.pairwise import pairwise_predictions

                bp = pairwise_predictions(sub, None, cache_dir=cache, progress=False)
                bs = solve(sub, bp, engine.opt)
                t, r = pose_error(bs.ee_T_cam[c], full.ee_T_cam[c])
                row["batch_frontend_to_full_mm_deg"] = [1e3 * t, r]
        rows.append(row)
        return sol

    engine.update = beside
    replay(session, order, seed)
    late = [r["max_abs_z"] for r in rows if "max_abs_z" in r and r["frames"] >= JACKKNIFE_BELOW]
    return {"order": order, "seed": seed, "steps": rows, "extra_steps": engine.extra_steps,
            "far_moves": engine.far_moves, "updates_cpu_s": sum(r["cpu_s"] for r in rows),
            "max_abs_z_from_15": max(late) if late else None,
            "median_abs_z_from_15": float(np.median(late)) if late else None,
            "beyond_1_sigma_from_15": sum(z > 1 for z in late), "compared_from_15": len(late)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", default="rwhe_kuka_2")
    ap.add_argument("--orders", default="recorded,guided:0,guided:1")
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--extra-step-sigmas", type=float, default=live_engine.EXTRA_STEP_SIGMAS)
    ap.add_argument("--tag", default="run")
    ap.add_argument("--batch-frontend", action="store_true",
                    help="also run the batch frontend on the frames so far, then solve, against the full result")
    add_work_args(ap, "live_real")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    live_engine.EXTRA_STEP_SIGMAS = args.extra_step_sigmas
    work, cache, out = work_dirs(args)
    runs = []
    for name in args.recordings.split(","):
        ds_dir, pname, _, full, _ = prepare(name, work, cache)
        for spec in args.orders.split(","):
            order, _, seed = spec.partition(":")
            if order == "file":
                order, seed = Path(seed).read_text().split(), 0
            r = track(ds_dir, pname, cache / name, order, int(seed or 0), args.every, full, args.batch_frontend)
            r.update(recording=name, extra_step_sigmas=args.extra_step_sigmas, spec=spec)
            runs.append(r)
            print(f"{name} {spec} (extra step from {args.extra_step_sigmas} sigma): from 15 poses |z| to solve "
                  f"max {r['max_abs_z_from_15']:.2f}, median {r['median_abs_z_from_15']:.2f}, "
                  f"{r['beyond_1_sigma_from_15']} of {r['compared_from_15']} beyond 1 sigma; extra steps "
                  f"{r['extra_steps']}, re-runs {r['far_moves']}; updates {r['updates_cpu_s']:.1f} CPU s", flush=True)
    (out / f"live_tracking_{args.tag}.json").write_text(json.dumps(runs, indent=1))


if __name__ == "__main__":
    main()
