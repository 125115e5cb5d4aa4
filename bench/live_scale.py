"""The guidance's scale goal (#22): on a simulated orbit like rwhe_kuka_2's, where the metric scale
cannot be observed, the guide must first propose motions toward or away from the scene, and within
3 guided poses the metric scale's sigma must fall below 0.5 %.

Per seed: ``simulate --trajectory orbit`` renders an orbit (cam0 circles the table's centre at
0.41 m, within 3 %, aiming within 3 mm of it, as rwhe_kuka_2's flange does; simulate.orbit_trajectory).
A ``LiveSession`` runs on its images with the pairwise RGB frontend (the one a live RGB capture
runs; the simulator's own predictions exist only for the frames it simulated, and an image frontend
also shows whether a proposed pose can be matched at all). Then, ``--steps`` times: the session's
best proposal (``Update.next_poses[0]``) is rendered by ``simulate.render_poses`` (the true scene and
mount), its flange pose reported with the simulator's robot noise, and added with ``add_frame``.
Reported per step: the proposal's kind, the metric scale and its sigma (%), the largest total
sigma, and the hand-eye's error to the simulator's truth.

    .venv/bin/python bench/live_scale.py [--seeds 3] [--frames 28] [--width 640] [--steps 3]
        [--work /tmp/live_scale] [--out bench/results]

Writes ``OUT/live_scale.json`` and ``OUT/live_scale.md``.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # see bench/views_real.py: set before numpy loads

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import gtsam  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from calib3r_graph.geometry import pose_error  # noqa: E402
from calib3r_graph.io.dataset import pose_from_dict  # noqa: E402
from calib3r_graph.live.session import LiveSession  # noqa: E402
from calib3r_graph.simulate import SimOptions, render_poses, simulate  # noqa: E402

GOAL_SCALE_REL = 0.005
GOAL_STEPS = 3
SCALE_KINDS = ("toward", "away")


def robot_reported(E: gtsam.Pose3, opt: SimOptions, rng) -> gtsam.Pose3:
    """The flange pose an arm with the simulator's robot noise reports after moving to ``E``."""
    xi = np.r_[rng.normal(size=3) * np.radians(opt.robot_noise_deg), rng.normal(size=3) * opt.robot_noise_mm * 1e-3]
    return E.compose(gtsam.Pose3.Expmap(xi))


def row(tag, kind, up, session, truth) -> dict:
    out = {"step": tag, "kind": kind, "frames": len(up.frames), "message": up.message}
    if up.metric_scale:
        lam, sig = up.metric_scale["cam0"]
        mm, deg = up.largest()
        t, r = pose_error(gtsam.Pose3(np.array(up.ee_T_cam["cam0"])), truth)
        used = sum(1 for v in session.sol.base_T_cam if v.startswith("cam0/"))
        out.update({"scale": lam, "scale_sigma_pct": 100 * sig / abs(lam), "largest_sigma_mm": mm,
                    "largest_sigma_deg": deg, "error_mm": 1e3 * t, "error_deg": r, "views_used": used,
                    "scale_systematic_pct": 100 * session.sol.systematic["cam0"].scale_sigma_rel})
    out["next_kinds"] = list(up.next_kinds)
    return out


def run_seed(seed, args, work: Path) -> dict:
    opt = SimOptions(seed=seed, frames=args.frames, trajectory="orbit", width=args.width, height=args.width * 3 // 4)
    ds_dir = work / f"orbit_{seed}"
    if not (ds_dir / "dataset.yaml").exists():
        simulate(ds_dir, opt, progress=False)
    truth = pose_from_dict(yaml.safe_load((ds_dir / "ground_truth.yaml").read_text())["hand_eye"]["cam0"])
    out = work / f"session_{seed}"
    shutil.rmtree(out, ignore_errors=True)
    session = LiveSession(ds_dir, target_mm=args.target_mm, target_deg=args.target_deg, out=out,
                          cache_dir=work / f"cache_{seed}", seed=seed)
    t0 = time.perf_counter()
    up = None
    for f in session.poses_known:  # the orbit, as recorded
        up = session.add_frame(f, images={"cam0": str(ds_dir / "images" / "cam0" / f"{f}.png")})
    steps = [row("orbit", "recorded", up, session, truth)]
    rng = np.random.default_rng(seed)
    for k in range(args.steps):
        if not up.next_poses:
            steps.append({"step": k + 1, "kind": None, "message": "no proposal"})
            break
        E, kind = gtsam.Pose3(np.array(up.next_poses[0])), up.next_kinds[0]
        img = render_poses(ds_dir, {"next": E}, seed=1000 * seed + k)["next"]
        up = session.add_frame(f"guided{k + 1}", robot_reported(E, opt, rng), images=img)
        steps.append(row(k + 1, kind, up, session, truth))
    guided = [s for s in steps[1:] if "scale_sigma_pct" in s]
    first = steps[1]["kind"] if len(steps) > 1 else None
    reached = next((s["step"] for s in guided if s["scale_sigma_pct"] < 100 * GOAL_SCALE_REL), None)
    return {"seed": seed, "frames": args.frames, "width": args.width, "steps": steps, "wall_s": time.perf_counter() - t0,
            "first_kind": first, "scale_goal_step": reached,
            "goal": bool(first in SCALE_KINDS and reached is not None and reached <= GOAL_STEPS)}


def table(result) -> str:
    lines = [f"Command: `{result['command']}`", "",
             "| seed | step | proposal kind | frames (views used) | metric scale σ (%) | of it systematic (%) | "
             "largest σ (mm / °) | error to truth (mm / °) |", "|---|---|---|---|---|---|---|---|"]
    for r in result["runs"]:
        for s in r["steps"]:
            if "scale_sigma_pct" not in s:
                lines.append(f"| {r['seed']} | {s['step']} | {s['kind']} | – | {s['message']} | | | |")
                continue
            lines.append(f"| {r['seed']} | {s['step']} | {s['kind']} | {s['frames']} ({s['views_used']}) | "
                         f"{s['scale_sigma_pct']:.2f} | {s['scale_systematic_pct']:.2f} | "
                         f"{s['largest_sigma_mm']:.2f} / {s['largest_sigma_deg']:.3f} | "
                         f"{s['error_mm']:.2f} / {s['error_deg']:.3f} |")
    lines += ["", "| seed | first proposal | scale σ < 0.5 % at guided pose | goal |", "|---|---|---|---|"]
    for r in result["runs"]:
        lines.append(f"| {r['seed']} | {r['first_kind']} | {r['scale_goal_step'] or '–'} | "
                     f"{'met' if r['goal'] else 'NOT met'} |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3, help="orbits (scenes and trajectories), seeds 0..N-1")
    ap.add_argument("--frames", type=int, default=28, help="orbit frames before the guided ones (rwhe_kuka_2 has 28)")
    ap.add_argument("--width", type=int, default=640, help="image width (height 3/4 of it)")
    ap.add_argument("--steps", type=int, default=GOAL_STEPS, help="guided poses")
    ap.add_argument("--target-mm", type=float, default=0.5)
    ap.add_argument("--target-deg", type=float, default=0.05)
    ap.add_argument("--work", default="/tmp/live_scale")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results"))
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR, format="%(levelname)s: %(message)s")
    work, out = Path(args.work), Path(args.out)
    work.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    result = {"command": " ".join(sys.argv), "runs": []}
    for seed in range(args.seeds):
        r = run_seed(seed, args, work)
        result["runs"].append(r)
        print(f"seed {seed}: first {r['first_kind']}, scale sigma "
              + " -> ".join(f"{s['scale_sigma_pct']:.2f}%" for s in r["steps"] if "scale_sigma_pct" in s)
              + f" ({'goal met' if r['goal'] else 'goal NOT met'}, {r['wall_s']:.0f} s)", flush=True)
        (out / "live_scale.json").write_text(json.dumps(result, indent=1, default=float))
    (out / "live_scale.md").write_text(table(result))
    print(table(result))


if __name__ == "__main__":
    main()
