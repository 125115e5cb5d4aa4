"""The live speed goal at the length it is set for, on a recording longer than that.

The goal: all the updates of a 30-frame replay together cost at most 3x one batch solve. A replay of
the first N frames of an order is the first N updates of the whole replay (the engine never sees
the frames after) and then ``finish``, which is ``solve`` on those N frames and their predictions.
So the orders of ``bench/live_real.py``'s replays (their ``frames_order``, the arrival order, in its
``live_real.json``) are cut to their first N frames and replayed as fixed orders; per replay the
CPU of all its updates, ``finish`` included, against that ``finish`` (``solve`` under the same
load, as ``live_real``'s column "all updates / the replay's own final solve").

Why it is worth its own figure: an update linearises every pair so far, so the updates' sum grows
with the square of the frames while one solve grows with the frames, and the ratio with N
(tabb_ds1's 88-frame replays: 6.6-6.8x where its 30-frame ones are measured here).

    .venv/bin/python bench/live_prefix.py --recording tabb_ds1 --frames 30 --runs 6
"""

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _workdirs import add_work_args, work_dirs  # noqa: E402
from live_real import prepare, run_order  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--recording", default="tabb_ds1")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--runs", type=int, default=6, help="replays per order kind (recorded has one)")
    ap.add_argument("--orders-from", default=str(Path(__file__).resolve().parent / "results" / "live_real.json"),
                    help="live_real.json whose replays' arrival orders are cut")
    add_work_args(ap, "live_real")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s: %(message)s")
    work, cache, out = work_dirs(args)
    full = json.loads(Path(args.orders_from).read_text())["recordings"][args.recording]
    ds_dir, pname, _, ref, (batch_s, batch_cpu_s) = prepare(args.recording, work, cache)
    print(f"{args.recording}: batch solve of all {full['frames']} frames {batch_cpu_s:.1f} CPU s", flush=True)
    rows, taken = [], {}
    for r in full["runs"]:
        kind = r["order"]
        if taken.get(kind, 0) >= (1 if kind == "recorded" else args.runs):
            continue
        taken[kind] = taken.get(kind, 0) + 1
        order = r["frames_order"][:args.frames]
        t = time.perf_counter()
        run = run_order(ds_dir, pname, cache / args.recording, ref, "file", 0, order)
        cpu = [s["cpu_s"] for s in run["steps"]]
        whole = [s["cpu_s"] for s in r["steps"]]
        row = {"order": kind, "seed": r["seed"], "frames": len(order), "updates_cpu_s": float(sum(cpu)),
               "finish_cpu_s": float(cpu[-1]), "ratio": float(sum(cpu) / cpu[-1]),
               "median_update_cpu_s": float(np.median(cpu[:-1])),
               "whole_replay_ratio": float(sum(whole) / whole[-1]), "whole_frames": len(r["frames_order"]),
               "final_max_abs_z_vs_full": max((abs(v) for c in run["final_z"].values() for v in c), default=None)}
        rows.append(row)
        print(f"  {kind} {r['seed']}: first {len(order)} frames: all updates {row['updates_cpu_s']:.1f} CPU s, "
              f"finish {row['finish_cpu_s']:.1f} s, {row['ratio']:.2f}x (the whole {row['whole_frames']}-frame "
              f"replay: {row['whole_replay_ratio']:.2f}x; {time.perf_counter() - t:.0f} s)", flush=True)
    result = {"command": " ".join(sys.argv), "recording": args.recording, "frames": args.frames,
              "batch_solve_cpu_s_all_frames": batch_cpu_s, "runs": rows}
    (out / "live_prefix.json").write_text(json.dumps(result, indent=1))
    lines = [f"Command: `{result['command']}`", "",
             f"{args.recording}: replays cut to their first {args.frames} frames (the orders of "
             f"`{Path(args.orders_from).name}`), CPU of all updates with `finish` against that `finish` (`solve` on "
             f"the same {args.frames} frames, the same load), and the same ratio of the whole replay:", "",
             "| order | replays | all updates / own finish (median, range) | median update CPU (s) | "
             "whole replay's ratio (median) |", "|---|---|---|---|---|"]
    for kind in dict.fromkeys(r["order"] for r in rows):
        rs = [r for r in rows if r["order"] == kind]
        q = [r["ratio"] for r in rs]
        lines.append(f"| {kind} | {len(rs)} | {np.median(q):.2f}× ({min(q):.2f}–{max(q):.2f}) | "
                     f"{np.median([r['median_update_cpu_s'] for r in rs]):.2f} | "
                     f"{np.median([r['whole_replay_ratio'] for r in rs]):.2f}× ({rs[0]['whole_frames']} frames) |")
    (out / "live_prefix.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
