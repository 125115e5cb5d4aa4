"""How far ``solve``'s two IRLS rounds are from the re-weighting's fixed point, on every recording.

``solve`` re-weights twice (``SolveOptions.irls_rounds = 2``), then runs the noise-calibrated round.
The live engine goes on re-weighting, one round a frame (live/engine.py), so where two rounds are
not a fixed point the live path and ``solve`` aim at different points. Per recording: ``solve``
with 2, 3, 4, 6, 8, 12 and 16 re-weighting rounds, the move of ee_T_cam from the 2-round result in
mm, degrees and in the 2-round result's own total sigma per ee axis, the matches kept, and the CPU
time.

    .venv/bin/python bench/irls_rounds.py [--recordings rwhe_kuka_1,rwhe_kuka_2,tabb_ds1,sim]
        [--rounds 2,3,4,6,8,12,16] [--work /tmp/live_real] [--cache /tmp/live_real/cache]

Uses ``bench/live_real.py``'s prepared recordings (the same work and cache folders). Writes
``OUT/irls_rounds.json`` and ``OUT/irls_rounds.md``.
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _workdirs import add_work_args, work_dirs  # noqa: E402
from live_real import ee_z, prepare  # noqa: E402
from calib3r_graph.io.dataset import load_dataset  # noqa: E402
from calib3r_graph.solver.solve import SolveOptions, solve  # noqa: E402
from calib3r_graph.solver.graph import NoiseOptions  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", default="rwhe_kuka_1,rwhe_kuka_2,tabb_ds1,sim")
    ap.add_argument("--rounds", default="2,3,4,6,8,12,16")
    add_work_args(ap, "live_real")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    work, cache, out = work_dirs(args)
    rounds = [int(x) for x in args.rounds.split(",")]
    table, rows = {}, ["Command: `.venv/bin/python bench/irls_rounds.py`", "",
                       "| recording | rounds | move mm / deg | largest move in sigma (ee axis) | matches kept | CPU s |",
                       "|---|---|---|---|---|---|"]
    for name in args.recordings.split(","):
        ds_dir, _, preds, ref, (_, ref_cpu) = prepare(name, work, cache)  # ref: solve with its own options
        ds = load_dataset(ds_dir)
        opt = SolveOptions(noise=NoiseOptions(pixel_sigma_px=float(preds.info.get("match_noise_px", 1.0))),
                           progress=False)
        res = []
        for k in rounds:
            if k == opt.irls_rounds:  # prepare's solve, the same options
                sol, cpu = ref, ref_cpu
            else:
                t = time.process_time()
                sol = solve(ds, preds, dataclasses.replace(opt, irls_rounds=k))
                cpu = time.process_time() - t
            c = sorted(sol.ee_T_cam)[0]
            res.append((k, sol.ee_T_cam[c], np.asarray(sol.covariance[c]), sol.stats["matches_used"], cpu))
        X0, C0 = res[0][1], res[0][2]
        table[name] = []
        for k, X, _, kept, cpu in res:
            z = ee_z(X, X0, C0)
            d = gtsam.Pose3.Logmap(X0.between(X))
            axis = ["rx", "ry", "rz", "x", "y", "z"][int(np.argmax(np.abs(z)))]
            table[name].append({"rounds": k, "move_mm": 1e3 * float(np.linalg.norm(d[3:])),
                                "move_deg": float(np.degrees(np.linalg.norm(d[:3]))), "z": z.tolist(),
                                "matches_kept": int(kept), "cpu_s": cpu})
            rows.append(f"| {name} | {k} | {1e3 * np.linalg.norm(d[3:]):.2f} / {np.degrees(np.linalg.norm(d[:3])):.4f} "
                        f"| {np.abs(z).max():.2f} ({axis}) | {kept} | {cpu:.1f} |")
            print(rows[-1], flush=True)
    (out / "irls_rounds.json").write_text(json.dumps(table, indent=1))
    (out / "irls_rounds.md").write_text("\n".join(rows) + "\n")


if __name__ == "__main__":
    main()
