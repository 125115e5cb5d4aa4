"""How `solve` scales: wall time, LM iterations, time inside the Python factor callbacks and
peak memory, for 25-200 views (1-8 cameras... up to the simulator's 3 per flange, more views via
more frames) and 500-5000 matches per pair; plus the ratio of an end-to-end solve to ONE
vectorised numpy evaluation of all scene residuals (3D + 2D both ways), the floor that any
Python implementation pays per iteration.

    .venv/bin/python bench/solve_scaling.py            # full table (minutes)
    .venv/bin/python bench/solve_scaling.py --quick    # 25 and 50 views only

Writes bench/results/solve_scaling.json and solve_scaling.png.
"""

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CONFIGS = [  # (views, cameras, matches per pair); (25, 1, 1100) is the goal's "25 poses, ~90k matches"
    (25, 1, 500), (25, 1, 1100), (25, 1, 2000), (25, 1, 5000), (50, 2, 2000), (100, 2, 2000), (100, 2, 5000), (200, 2, 2000),
]


def scene_floor_seconds(preds, observations, sol, repeats=5) -> float:
    """Best-of time of one vectorised evaluation of every 3D and 2D scene residual at the solution."""
    views = sorted(sol.base_T_cam)
    idx = {v: i for i, v in enumerate(views)}
    R = np.array([sol.base_T_cam[v].rotation().matrix() for v in views])
    t = np.array([sol.base_T_cam[v].translation() for v in views])
    s = np.array([sol.depth_scale[v] for v in views])
    K = np.array([preds.views[v].K for v in views])
    ia = np.concatenate([[idx[o.view_a]] * len(o) for o in observations])
    ib = np.concatenate([[idx[o.view_b]] * len(o) for o in observations])
    pa = np.concatenate([o.pts_a for o in observations])
    pb = np.concatenate([o.pts_b for o in observations])
    uva = np.concatenate([o.uv_a for o in observations])
    uvb = np.concatenate([o.uv_b for o in observations])

    def evaluate():
        Xa = np.einsum("nij,nj->ni", R[ia], s[ia, None] * pa) + t[ia]  # points in base
        Xb = np.einsum("nij,nj->ni", R[ib], s[ib, None] * pb) + t[ib]
        r3 = np.einsum("nji,nj->ni", R[ia], Xa - Xb) / s[ia, None]  # 3D, in camera a
        qb = np.einsum("nji,nj->ni", R[ib], Xa - t[ib])  # a's point in camera b
        qa = np.einsum("nji,nj->ni", R[ia], Xb - t[ia])
        r2b = np.einsum("nij,nj->ni", K[ib], qb)[:, :2] / qb[:, 2:3] - uvb
        r2a = np.einsum("nij,nj->ni", K[ia], qa)[:, :2] / qa[:, 2:3] - uva
        return r3, r2a, r2b

    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        evaluate()
        best = min(best, time.perf_counter() - t0)
    return best


def run_one(views: int, cameras: int, matches: int) -> dict:
    import factors.compression as comp
    from calib3r_graph.io.dataset import load_dataset
    from calib3r_graph.io.predictions import load_predictions
    from calib3r_graph.simulate import SimOptions, simulate
    from calib3r_graph.solver.observations import build_observations
    from calib3r_graph.solver.solve import SolveOptions, solve

    callback = {"seconds": 0.0, "calls": 0}
    original = comp.compressed_error

    def timed(*a, **k):
        t0 = time.perf_counter()
        try:
            return original(*a, **k)
        finally:
            callback["seconds"] += time.perf_counter() - t0
            callback["calls"] += 1

    comp.compressed_error = timed
    with tempfile.TemporaryDirectory() as tmp:
        root = simulate(Path(tmp) / "d", SimOptions(seed=1, frames=views // cameras, cameras=cameras, images=False,
                                                    matches_per_pair=matches), progress=False)
        ds = load_dataset(root)
        preds = load_predictions(root, "sim", ds.cameras, set(ds.frames))
        opt = SolveOptions(max_matches_per_pair=matches)
        t0 = time.perf_counter()
        sol = solve(ds, preds, opt)
        wall = time.perf_counter() - t0
        observations = build_observations(preds, matches, seed=0)
        floor = scene_floor_seconds(preds, observations, sol)
    return {"views": len(sol.base_T_cam), "cameras": cameras, "matches_per_pair": matches,
            "pairs": sol.stats["pairs_used"], "matches": sol.stats["matches_total"], "solve_s": wall,
            "lm_iterations": sum(r["iterations"] for r in sol.stats["rounds"]),
            "callback_s": callback["seconds"], "callback_calls": callback["calls"],
            "timings_s": sol.stats["timings_s"], "floor_s": floor, "ratio_to_floor": wall / floor,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--one", nargs=3, type=int, help=argparse.SUPPRESS)  # views cameras matches, in a subprocess
    args = ap.parse_args()
    if args.one:
        print(json.dumps(run_one(*args.one)))
        return
    configs = [c for c in CONFIGS if c[0] <= 50] if args.quick else CONFIGS
    rows = []
    print(f"{'views':>5} {'cams':>4} {'m/pair':>6} {'pairs':>5} {'matches':>8} {'solve s':>8} {'LM it':>5} "
          f"{'callback s':>10} {'floor ms':>8} {'ratio':>6} {'peak MB':>8}")
    for v, c, m in configs:
        out = subprocess.run([sys.executable, __file__, "--one", str(v), str(c), str(m)], capture_output=True,
                             text=True, cwd=ROOT)
        if out.returncode != 0:
            print(out.stderr[-2000:], file=sys.stderr)
            continue
        r = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(r)
        print(f"{r['views']:5d} {r['cameras']:4d} {m:6d} {r['pairs']:5d} {r['matches']:8d} {r['solve_s']:8.2f} "
              f"{r['lm_iterations']:5d} {r['callback_s']:10.2f} {r['floor_s'] * 1e3:8.1f} {r['ratio_to_floor']:6.0f} "
              f"{r['peak_rss_mb']:8.0f}", flush=True)
    out_dir = Path(__file__).parent / "results"
    out_dir.mkdir(exist_ok=True)
    (out_dir / "solve_scaling.json").write_text(json.dumps(rows, indent=2))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    x = [r["matches"] for r in rows]
    ax.loglog(x, [r["solve_s"] for r in rows], "o-", label="solve (end to end)")
    ax.loglog(x, [r["callback_s"] for r in rows], "s--", label="inside Python factor callbacks")
    for r in rows:
        ax.annotate(f"{r['views']}v", (r["matches"], r["solve_s"]), fontsize=7)
    ax.set_xlabel("matches in the graph")
    ax.set_ylabel("seconds (2 cores)")
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out_dir / "solve_scaling.png", dpi=110)


if __name__ == "__main__":
    main()
