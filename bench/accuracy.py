"""Accuracy of `solve` on simulated foundation-model-like data, for the configurations of
the project's accuracy goals. Prints a table and writes bench/results/accuracy.json.

    .venv/bin/python bench/accuracy.py [--seeds 3]
"""

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from calib3r_graph.evaluation.evaluate import hand_eye_errors  # noqa: E402
from calib3r_graph.io.dataset import load_dataset, load_ground_truth  # noqa: E402
from calib3r_graph.io.predictions import load_predictions  # noqa: E402
from calib3r_graph.simulate import SimOptions, simulate  # noqa: E402
from calib3r_graph.solver.solve import SolveOptions, solve  # noqa: E402

CONFIGS = [  # name, simulator options, goal (mm, deg)
    ("1 camera, 25 poses", dict(frames=25), (2.0, 0.15)),
    ("3 cameras, 20 poses", dict(frames=20, cameras=3), (3.0, 0.2)),
    ("1 camera, 6 poses", dict(frames=6), (8.0, 0.5)),
    ("1 camera, 12 poses, robot in mm", dict(frames=12, unit="mm"), (2.0, 0.15)),
]


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args()
    rows = []
    for name, kw, (goal_mm, goal_deg) in CONFIGS:
        et, er, secs = [], [], []
        for seed in range(args.seeds):
            with tempfile.TemporaryDirectory() as tmp:
                root = simulate(Path(tmp) / "d", SimOptions(seed=100 + seed, images=False, **kw), progress=False)
                ds = load_dataset(root)
                preds = load_predictions(root, "sim", ds.cameras, set(ds.frames))
                t = time.perf_counter()
                sol = solve(ds, preds, SolveOptions())
                secs.append(time.perf_counter() - t)
                for e in hand_eye_errors(sol.ee_T_cam, load_ground_truth(root)).values():
                    et.append(e["e_t_m"] * 1e3)
                    er.append(np.degrees(e["e_theta_rad"]))
        rows.append({"config": name, "goal_mm": goal_mm, "goal_deg": goal_deg, "e_t_mm_mean": float(np.mean(et)),
                     "e_t_mm_max": float(np.max(et)), "e_r_deg_mean": float(np.mean(er)),
                     "e_r_deg_max": float(np.max(er)), "solve_s_mean": float(np.mean(secs)), "runs": args.seeds})
    print(f"{'configuration':34s} {'e_t mean/max (mm)':>18s} {'e_r mean/max (deg)':>19s} {'goal':>14s} {'solve s':>8s}")
    for r in rows:
        print(f"{r['config']:34s} {r['e_t_mm_mean']:8.2f}/{r['e_t_mm_max']:<8.2f} {r['e_r_deg_mean']:9.3f}/"
              f"{r['e_r_deg_max']:<8.3f} {r['goal_mm']:5.1f}/{r['goal_deg']:<5.2f}  {r['solve_s_mean']:7.1f}")
    out = Path(__file__).parent / "results" / "accuracy.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
