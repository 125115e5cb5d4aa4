"""``calib3r-graph live``: the command's logic (calib3r_graph/cli.py only parses the arguments)."""

import sys
from pathlib import Path

from calib3r_graph.errors import InputError


def parse_box(text):
    """--box's (lo, hi) corners in the base frame (m), or None."""
    if not text:
        return None
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 6 or any(a >= b for a, b in zip(v[:3], v[3:])):
        raise InputError("--box", "must be x0,y0,z0,x1,y1,z1 with x0 < x1, y0 < y1, z0 < z1 (metres)")
    return v[:3], v[3:]


def _columns(rows) -> str:
    """Rows of strings as aligned columns, one line each (numbers right-aligned)."""
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n  ".join(" ".join(c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths)))
                        for r in rows)


def run_live(args, noise_from_args):
    from calib3r_graph.io.predictions import available_predictions
    from calib3r_graph.live.run import replay, watch
    from calib3r_graph.live.session import LiveSession, session_dataset
    from calib3r_graph.solver.solve import SolveOptions

    out = Path(args.out)
    if (out / "live.jsonl").exists() and not args.resume:
        raise InputError(out / "live.jsonl", "exists: use another --out (or --watch --resume to continue it)")
    if args.resume and not args.watch:
        raise InputError("--resume", "continues a --watch session; a replay starts from its first frame")
    if (args.poses or args.pose_format or args.pose_key) and not args.watch:
        raise InputError("--poses", "is for --watch; a replay reads the dataset's own robot poses")
    ds = session_dataset(args.dataset)
    poses = None
    if args.poses:  # checked before anything is written
        from calib3r_graph.live.poses import PoseFiles

        poses = PoseFiles(args.poses, args.pose_format, args.pose_key, args.unit or ds.robot_unit, args.direction)
    name = args.predictions
    if name is None:
        found = available_predictions(ds.root)
        name = found[0] if len(found) == 1 else ("sim" if "sim" in found else None)
    info = {}
    if name:
        import json

        p = ds.root / "predictions" / name / "info.json"
        info = json.loads(p.read_text()) if p.is_file() else {}
    opt = SolveOptions(noise=noise_from_args(args, info), progress=False)
    session = LiveSession(args.dataset, args.target_mm, args.target_deg, out=out, predictions=name, opt=opt,
                          k_next=args.next, margin_m=args.margin_m, box=parse_box(args.box),
                          pixel_from_predictions=args.pixel_sigma_px is None, next_pose_format=poses)
    source = f"predictions/{name}" if name else "the pairwise frontend on each new image"
    print(f"live: {ds.root} ({source}); target {args.target_mm} mm / {args.target_deg} deg; writing {out}",
          file=sys.stderr)

    def show(up):
        print(up.status_line(), flush=True)

    if args.replay:
        ups = replay(session, args.replay, args.seed, on_update=show)
        last = ups[-1] if ups else None
    else:
        try:
            last = watch(session, args.poll_s, on_update=show, max_idle_s=args.idle_s, resume=args.resume,
                         poses=poses)
        except KeyboardInterrupt:
            print(f"live: interrupted; {out} holds the state after the last update (--resume continues it)",
                  file=sys.stderr)
            return
    if last is not None and last.next_poses:
        print(f"next poses (base_T_ee, best first, {session.next_pose_format.describe()}; also in next_poses.csv):")
        rows = session.next_pose_rows(last)
        print("  " + _columns([["kind"] + rows[0]] + [[k] + r for k, r in zip(last.next_kinds, rows[1:])]))
    wrote = [f for f in ("calibration.json", "next_poses.csv", "live.jsonl") if (out / f).is_file()]
    print(f"wrote {out}/{', '.join(wrote)}" + ("" if "calibration.json" in wrote else
                                               " (no calibration.json: no update could solve these frames)"))
