"""Wall time of ``calib3r-graph solve`` as a user sees it (a fresh process: Python start-up, imports,
solve, outputs) beside the time spent in-process, on the shipped sample and on a 25-pose simulated
dataset with images. Prints a table and writes bench/results/cli_time.json.

    .venv/bin/python bench/cli_time.py [--repeats 3] [--frames 25]

Columns (seconds, wall / CPU = user + system, the best of the repeats; on a shared machine the CPU
time is the steadier figure):
  cli        ``python -m calib3r_graph.cli -q solve DATASET --out DIR`` in a fresh process
  imports    a fresh process that only imports what ``solve`` imports (cli, solve, results, report)
  in-proc    ``cli.main([...])`` again in a process that has already imported everything
  load, solve, cloud, report   the parts of in-proc: loading the dataset and predictions, the solver,
             building and writing reconstruction.ply, and report.html
"""

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
IMPORTS = ("import calib3r_graph.cli, calib3r_graph.io.dataset, calib3r_graph.io.predictions, "
           "calib3r_graph.solver.solve, calib3r_graph.io.results\n"
           "try:\n    import calib3r_graph.report\nexcept ImportError:\n    pass")


class Clock:
    """Wall time and CPU time (user + system, this process and its finished children)."""

    def __enter__(self):
        self.t, self.c = time.perf_counter(), self._cpu()
        return self

    def __exit__(self, *exc):
        self.wall, self.cpu = time.perf_counter() - self.t, self._cpu() - self.c

    @staticmethod
    def _cpu():
        s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
        return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def _fresh(code: str) -> tuple:
    with Clock() as c:
        subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True)
    return c.wall, c.cpu


def _cli(dataset: Path, out: Path, extra=()) -> tuple:
    with Clock() as c:
        subprocess.run([sys.executable, "-m", "calib3r_graph.cli", "-q", "solve", str(dataset), "--out", str(out),
                        *extra], cwd=REPO, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return c.wall, c.cpu


def _in_process(dataset: Path, out: Path) -> dict:
    """Runs in this process (imports already paid): main() and its parts."""
    import contextlib
    import io

    import numpy as np

    from calib3r_graph.cli import main
    from calib3r_graph.io.dataset import load_dataset
    from calib3r_graph.io.predictions import choose_predictions, load_predictions
    from calib3r_graph.io.results import point_cloud

    try:
        from calib3r_graph.io.results import write_ply
    except ImportError:  # before issue 17: Open3D wrote the cloud
        def write_ply(path, points, colors):
            import open3d as o3d

            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
            pcd.colors = o3d.utility.Vector3dVector(colors)
            o3d.io.write_point_cloud(str(path), pcd, write_ascii=False)
    from calib3r_graph.solver.solve import SolveOptions, solve

    sink = io.StringIO()
    out_d = {}
    with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
        with Clock() as c:
            main(["-q", "solve", str(dataset), "--out", str(out)])
        out_d["in_process"] = (c.wall, c.cpu)
        with Clock() as c:
            ds = load_dataset(dataset)
            preds = load_predictions(ds.root, choose_predictions(ds, None), ds.cameras, set(ds.frames))
        out_d["load"] = (c.wall, c.cpu)
        with Clock() as c:
            sol = solve(ds, preds, SolveOptions(progress=False))
        out_d["solve"] = (c.wall, c.cpu)
        with Clock() as c:
            pcd = point_cloud(ds, preds, sol)
            write_ply(out / "cloud.ply", np.asarray(pcd.points), np.asarray(pcd.colors))
        out_d["cloud"] = (c.wall, c.cpu)
        try:
            from calib3r_graph.io.results import calibration_json, summary_text
            from calib3r_graph.report import solve_report_writer
        except ImportError:
            out_d["report"] = None
        else:
            with Clock() as c:
                solve_report_writer(ds, preds, sol)(out, calibration_json(sol, preds.name),
                                                    summary_text(sol, ds, preds.name), pcd)
            out_d["report"] = (c.wall, c.cpu)
    return out_d


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--frames", type=int, default=25)
    args = ap.parse_args()
    sys.path.insert(0, str(REPO))
    from calib3r_graph.simulate import SimOptions, simulate

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        datasets = [("sample (16 views, 2 cameras)", REPO / "datasets" / "sample"),
                    (f"simulated, {args.frames} poses, 1 camera, 640x480 images",
                     simulate(tmp / "sim", SimOptions(seed=1, frames=args.frames), progress=False))]
        best = lambda xs: tuple(min(x[k] for x in xs) for k in range(2))  # noqa: E731
        imports = best([_fresh(IMPORTS) for _ in range(args.repeats)])
        python = best([_fresh("pass") for _ in range(args.repeats)])
        has_report = "--no-report" in subprocess.run([sys.executable, "-m", "calib3r_graph.cli", "solve", "--help"],
                                                     cwd=REPO, capture_output=True, text=True).stdout
        for name, root in datasets:
            cli = best([_cli(root, tmp / "out") for _ in range(args.repeats)])
            bare = ["--no-cloud"] + (["--no-report"] if has_report else [])
            cli_bare = best([_cli(root, tmp / "out", bare) for _ in range(args.repeats)])
            parts = [_in_process(root, tmp / "out") for _ in range(args.repeats)]
            row = {"dataset": name, "cli": cli, "bare": cli_bare, "python_start": python, "imports": imports}
            for k in parts[0]:
                row[k] = None if parts[0][k] is None else best([p[k] for p in parts])
            rows.append(row)
    cols = ["cli", "bare", "imports", "in_process", "load", "solve", "cloud", "report"]
    print(f"{'dataset':48s} " + " ".join(f"{c:>11s}" for c in cols))
    for r in rows:
        cells = [f"{r[c][0]:5.2f}/{r[c][1]:5.2f}" if r[c] is not None else f"{'–':>11s}" for c in cols]
        print(f"{r['dataset']:48s} " + " ".join(cells))
    print(f"seconds, wall/CPU, best of {args.repeats}; python start-up alone {rows[0]['python_start'][0]:.2f} s; "
          "'bare' is the CLI with --no-cloud --no-report")
    out = REPO / "bench" / "results" / "cli_time.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"repeats": args.repeats, "rows": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
