"""Speed of the pairwise frontend: rendered scenes of 15, 30 and 55 frames at 640x480, and two
public recordings: rwhe_kuka_1 (30 images of 1928x1208, SIFT at 1600 px) and tabb_ds1 (88 images
of 640x480), from images to predictions, nothing cached.

Per run: the images, the pairs matched against all pairs, the wall-clock and CPU seconds (the
machine may be shared: CPU seconds over the workers say what the frontend itself costs), the
seconds per image and the views the predictions keep. ``--all-pairs`` also runs every pair (the
frontend before pair selection, ``partners=0``) on the scenes of at most ``--all-pairs-max``
frames. The slope of log(seconds) against log(images) over the rendered scenes says how the
time grows (2 = quadratic). ``--solve`` also solves each rendered scene's predictions and gives
the hand-eye error to the truth. Prints a table and writes bench/results/frontend_speed.json.

    .venv/bin/python bench/frontend_speed.py [--frames 15,30,55] [--workers 2] [--all-pairs]
        [--all-pairs-max 30] [--solve] [--recordings rwhe_kuka_1,tabb_ds1] [--real ../shared/real]
        [--work /tmp/calib3r-frontend-speed]
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # the solver-free frontend: OpenCV threads instead

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from calib3r_graph.frontends.pairwise import PairwiseOptions, pairwise_predictions  # noqa: E402
from calib3r_graph.io.dataset import load_dataset, load_ground_truth  # noqa: E402


def rendered(work: Path, frames: int) -> Path:
    """A rendered 640x480 scene of ``frames`` frames, images and robot poses only (cached in work)."""
    from calib3r_graph.simulate import SimOptions, simulate

    root = work / f"sim{frames}"
    if not (root / "dataset.yaml").exists():
        shutil.rmtree(root, ignore_errors=True)
        simulate(root, SimOptions(seed=0, frames=frames, width=640, height=480), progress=False)
        shutil.rmtree(root / "predictions", ignore_errors=True)
        shutil.rmtree(root / "depth", ignore_errors=True)
    return root


# The public recordings, as bench/real.py imports them: (format, board's inner corners)
RECORDINGS = {"rwhe_kuka_1": ("rwhe", (28, 17)), "rwhe_kuka_2": ("rwhe", (24, 17)), "tabb_ds1": ("tabb", None)}


def recording(work: Path, real: Path, name: str) -> Path | None:
    """``calib3r-graph import`` of a public recording into work (cached), or None without it."""
    src = real / name
    if not src.is_dir():
        return None
    root = work / name
    if not (root / "dataset.yaml").exists():
        from calib3r_graph.importers import import_recording

        import_recording(RECORDINGS[name][0], src, root, RECORDINGS[name][1], progress=False)
    return root


def accuracy(ds, preds) -> dict:
    """The solve's hand-eye error to the rendered truth (mm, deg), as tests/test_pairwise.py solves."""
    from calib3r_graph.evaluation.evaluate import hand_eye_errors
    from calib3r_graph.solver.graph import NoiseOptions
    from calib3r_graph.solver.solve import SolveOptions, solve

    sol = solve(ds, preds, SolveOptions(noise=NoiseOptions(pixel_sigma_px=preds.info["match_noise_px"]),
                                        progress=False))
    e = hand_eye_errors(sol.ee_T_cam, load_ground_truth(ds.root))["cam0"]
    return {"e_t_mm": 1e3 * e["e_t_m"], "e_theta_deg": float(np.degrees(e["e_theta_rad"]))}


def run(name: str, root: Path, partners: int, workers: int, solve: bool = False) -> dict:
    ds = load_dataset(root)
    opt = PairwiseOptions(partners=partners)
    wall, cpu = time.perf_counter(), time.process_time()
    preds = pairwise_predictions(ds, opt=opt, progress=False, workers=workers)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    info = preds.info
    acc = accuracy(ds, preds) if solve and load_ground_truth(root) is not None else {}
    cam = next(iter(ds.cameras.values()))
    return {"scene": name, "images": info["images"], "size": f"{cam.width}x{cam.height}",
            "selection": "every pair" if partners == 0 else f"{partners} partners",
            "pairs_matched": info["pairs_matched"], "pairs_possible": info["pairs_possible"],
            "pairs_per_round": info["pairs_matched_per_round"], "verified": info["verified_pairs"],
            "robot_consistent": info["robot_consistent_pairs"], "views": info["views"],
            "unusable": info["unusable_views"], "seconds": wall, "cpu_seconds": cpu,
            "seconds_per_image": wall / info["images"], "cpu_seconds_per_image": cpu / info["images"],
            "stages": info["seconds"], **acc}


def table(rows: list) -> str:
    lines = ["| scene | images | selection | pairs matched / all | views kept | s | CPU s | s / image | CPU s / image "
             "| solve's error to truth |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        err = f"{r['e_t_mm']:.2f} mm / {r['e_theta_deg']:.3f} deg" if "e_t_mm" in r else "–"
        lines.append(f"| {r['scene']} ({r['size']}) | {r['images']} | {r['selection']} | {r['pairs_matched']} / "
                     f"{r['pairs_possible']} | {r['views']} | {r['seconds']:.1f} | {r['cpu_seconds']:.1f} | "
                     f"{r['seconds_per_image']:.2f} | {r['cpu_seconds_per_image']:.2f} | {err} |")
    return "\n".join(lines)


def growth(rows: list) -> float | None:
    """Slope of log(CPU seconds) against log(images) over the rendered scenes with pair selection."""
    pts = [(r["images"], r["cpu_seconds"]) for r in rows if r["scene"].startswith("rendered")
           and r["selection"] != "every pair"]
    if len(pts) < 2:
        return None
    x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(x, y, 1)[0])


def cli():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", default="15,30,55")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--partners", type=int, default=PairwiseOptions().partners)
    p.add_argument("--all-pairs", action="store_true", help="also match every pair, for comparison")
    p.add_argument("--all-pairs-max", type=int, default=30, help="... on the scenes of at most this many frames")
    p.add_argument("--real", default=str(ROOT.parent / "shared" / "real"))
    p.add_argument("--recordings", default="rwhe_kuka_1,tabb_ds1",
                   help=f"public recordings to time, of {', '.join(RECORDINGS)} ('' for none)")
    p.add_argument("--solve", action="store_true", help="also solve the rendered scenes and give the error to the truth")
    p.add_argument("--work", default="/tmp/calib3r-frontend-speed")
    p.add_argument("--out", default=str(ROOT / "bench" / "results" / "frontend_speed.json"))
    args = p.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s: %(message)s")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    scenes = [(f"rendered {n}", rendered(work, n)) for n in map(int, args.frames.split(","))]
    for name in args.recordings.split(",") if args.recordings else []:
        if (root := recording(work, Path(args.real), name)) is not None:
            scenes.append((name, root))
    rows = []
    for name, root in scenes:
        modes = [args.partners]
        if args.all_pairs and load_dataset(root).frames.__len__() <= args.all_pairs_max:
            modes.append(0)
        for partners in modes:
            print(f"[frontend_speed] {name}, {'every pair' if partners == 0 else f'{partners} partners'} ...",
                  file=sys.stderr, flush=True)
            rows.append(run(name, root, partners, args.workers, args.solve))
    slope = growth(rows)
    text = table(rows) + (f"\n\nCPU time grows as images^{slope:.2f} over the rendered scenes" if slope else "")
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"command": "bench/frontend_speed.py " + " ".join(sys.argv[1:]), "workers": args.workers,
                               "cpu_growth_exponent": slope, "runs": rows}, indent=1))


if __name__ == "__main__":
    cli()
