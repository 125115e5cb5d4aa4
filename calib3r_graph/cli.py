"""Command-line interface: a thin layer over the library.

Every domain error becomes one line on stderr and its exit code (see
calib3r_graph.errors); tracebacks only with --debug.
"""

import argparse
import dataclasses
import logging
import os
import sys
import traceback
from pathlib import Path

# One BLAS thread unless the user says otherwise, set before numpy loads: the solver's dense
# matrices are small, and a second OpenBLAS thread made them up to 1000x slower on a busy
# 2-core machine (the sample's solve: 2.3 s wall with one thread, over 60 s with two under load).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from calib3r_graph import __version__  # noqa: E402
from calib3r_graph.errors import Calib3rError, InputError  # noqa: E402

log = logging.getLogger("calib3r_graph")


def _add_noise_args(p):
    from calib3r_graph.solver.graph import NoiseOptions

    d = NoiseOptions()
    g = p.add_argument_group("noise model (physical units)")
    g.add_argument("--pixel-sigma-px", type=float, default=None,
                   help="match noise on the frontend's grid (default: the predictions' info.json "
                        f"match_noise_px, else {d.pixel_sigma_px})")
    g.add_argument("--depth-sigma-rel", type=float, default=d.depth_sigma_rel, help="relative depth noise")
    g.add_argument("--robot-sigma-mm", type=float, default=d.robot_sigma_mm, help="flange position noise")
    g.add_argument("--robot-sigma-deg", type=float, default=d.robot_sigma_deg, help="flange orientation noise")
    g.add_argument("--rig-sigma-mm", type=float, default=d.rig_sigma_mm, help="rig non-rigidity, position")
    g.add_argument("--rig-sigma-deg", type=float, default=d.rig_sigma_deg, help="rig non-rigidity, orientation")
    g.add_argument("--depth-correction-sigma", type=float, default=d.depth_correction_sigma,
                   help="prior sigma of each view's smooth depth-correction coefficients (0 disables)")


def _noise_from_args(args, info: dict):
    from calib3r_graph.solver.graph import NoiseOptions

    px = args.pixel_sigma_px
    if px is None:
        px = float(info.get("match_noise_px", NoiseOptions().pixel_sigma_px))
    return NoiseOptions(pixel_sigma_px=px, depth_sigma_rel=args.depth_sigma_rel, robot_sigma_mm=args.robot_sigma_mm,
                        robot_sigma_deg=args.robot_sigma_deg, rig_sigma_mm=args.rig_sigma_mm,
                        rig_sigma_deg=args.rig_sigma_deg, depth_correction_sigma=args.depth_correction_sigma)


def cmd_solve(args):
    from calib3r_graph.io.results import write_results

    ds, preds, opt, sol = _solve_dataset(args)
    out = _out_dir(args)
    report = None
    if not args.no_report:
        from calib3r_graph.report import solve_report_writer

        report = solve_report_writer(ds, preds, sol, opt.noise)
    dense = _dense_step(args, ds, preds.name, sol) if args.dense else None
    summary = write_results(out, ds, preds, sol, write_cloud=not args.no_cloud, extra=report, dense=dense)
    print(summary, end="")
    print(f"  wrote {out}/calibration.json, trajectory.csv, summary.txt"
          + ("" if args.no_cloud else ", reconstruction.ply")
          + (", dense.ply, mesh.ply, dense.json" if args.dense else "")
          + ("" if args.no_report else ", report.html"))


def _dense_options(args):
    from calib3r_graph.dense import DenseOptions

    return DenseOptions(voxel_mm=args.voxel_mm, max_views=args.max_views, source=args.dense_source,
                        progress=not args.quiet)


def _dense_step(args, ds, predictions_name, sol):
    """solve --dense: the dense reconstruction in the staging folder, after trajectory.csv."""
    from calib3r_graph.dense.run import reconstruct, summary_lines
    from calib3r_graph.dense.views import SolveResult

    def run(stage):
        result = SolveResult({v: T.matrix() for v, T in sol.base_T_cam.items()},
                             {c: X.matrix() for c, X in sol.ee_T_cam.items()}, predictions_name, Path(stage))
        figures = reconstruct(ds, result, _dense_options(args), stage)
        return figures, summary_lines(figures)
    return run


def cmd_reconstruct(args):
    from calib3r_graph.dense.run import reconstruct_result, summary_lines

    figures = reconstruct_result(args.result, args.dataset, _dense_options(args))
    if not args.no_report:  # the report rebuilt from the folder's files, with the dense cloud
        from calib3r_graph.report import write_result_report

        write_result_report(args.result, args.dataset)
    print(summary_lines(figures), end="")
    print(f"  wrote {args.result}/dense.ply, mesh.ply, dense.json" + ("" if args.no_report else ", report.html"))


def _add_dense_args(p):
    g = p.add_argument_group("dense reconstruction (docs/dense.md)")
    g.add_argument("--voxel-mm", type=float, default=2.0, help="voxel size of the fused cloud and mesh (default 2)")
    g.add_argument("--max-views", type=int, help="use at most N views, spread over the recording (default: all)")
    g.add_argument("--dense-source", choices=["auto", "stereo", "depth", "predictions"], default="auto",
                   help="per-view depth: sensor depth (depth/), dense predictions with the solve's depth scale, or "
                        "SGBM stereo from the images; auto: the first the dataset has (default)")


def cmd_simulate(args):
    from calib3r_graph.simulate import SimOptions, simulate

    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.force:
        raise InputError(out, "exists and is not empty (use --force to write into it)")
    opt = SimOptions(seed=args.seed, frames=args.frames, cameras=args.cameras, images=not args.no_images,
                     pattern=args.pattern, width=args.width, height=args.height, unit=args.unit,
                     depth_distortion=args.depth_distortion, outlier_fraction=args.outlier_fraction,
                     matches_per_pair=args.matches_per_pair, prediction_downsample=args.prediction_downsample,
                     robot_noise_mm=args.robot_noise_mm, robot_noise_deg=args.robot_noise_deg,
                     trajectory=args.trajectory)
    if not 1 <= opt.cameras <= 3:
        raise InputError("--cameras", "must be 1, 2 or 3")
    if opt.frames < 2:
        raise InputError("--frames", "must be at least 2")
    simulate(out, opt, progress=not args.quiet)
    print(f"wrote {out} ({opt.frames} frames x {opt.cameras} camera(s), predictions/sim, ground_truth.yaml)")


def _out_dir(args) -> Path:
    """--out, or results/<dataset name>."""
    return Path(args.out) if args.out else Path("results") / Path(args.dataset).resolve().name


def _announce(line: str):
    """Tell the user, on stderr (also with -q), e.g. which frontend made the predictions."""
    print(line, file=sys.stderr)


def _solve_dataset(args):
    from calib3r_graph.frontends import ensure_predictions
    from calib3r_graph.io.dataset import load_dataset
    from calib3r_graph.io.predictions import load_predictions
    from calib3r_graph.solver.solve import SolveOptions, solve

    ds = load_dataset(args.dataset, skip_missing=args.skip_missing)
    if getattr(args, "intrinsics_sigma_px", None):  # a stated prior on the intrinsics (solver/camera_model.py)
        from calib3r_graph.solver.camera_model import parse_intrinsics_sigma, with_params_sigma

        ds = with_params_sigma(ds, parse_intrinsics_sigma(args.intrinsics_sigma_px),
                               f"--intrinsics-sigma-px {args.intrinsics_sigma_px}")
    name = ensure_predictions(ds, args.predictions, progress=not args.quiet, announce=_announce)
    preds = load_predictions(ds.root, name, ds.cameras, set(ds.frames), skip_missing=args.skip_missing)
    opt = SolveOptions(noise=_noise_from_args(args, preds.info), max_matches_per_pair=args.max_matches_per_pair,
                       irls_rounds=args.irls_rounds, max_iterations=args.max_iterations,
                       reprojection=args.reprojection, init=args.init, jackknife=args.jackknife,
                       jackknife_method=getattr(args, "jackknife_method", None), jobs=args.jobs,
                       progress=not args.quiet)
    return ds, preds, opt, solve(ds, preds, opt)


def cmd_plan(args):
    """The next flange poses to record, ranked by the largest total sigma expected after each (the live
    guide's objective, solver/guidance.py): the --candidates file's, or without it the guide's own."""
    from calib3r_graph.io.dataset import load_dataset, read_robot_poses, write_robot_poses
    from calib3r_graph.io.output import atomic_write_json
    from calib3r_graph.io.results import largest_sigma, uncertainty_report
    from calib3r_graph.live.cli import parse_box
    from calib3r_graph.solver.guidance import candidate_poses, score_candidates
    from calib3r_graph.solver.uncertainty import MIN_CHECKED_POSES

    unit = load_dataset(args.dataset, skip_missing=args.skip_missing).robot_unit
    box = parse_box(args.box)
    candidates = None
    if args.candidates:  # read before solving: a bad file fails at once
        candidates = read_robot_poses(Path(args.candidates), unit, "the --candidates file")
    ds, preds, opt, sol = _solve_dataset(args)
    # the robot factors' noise as the solve calibrated it (its robot variance factor)
    robot_mm, robot_deg = sol.stats["noise_calibration"]["robot_sigma_used"]
    noise = dataclasses.replace(opt.noise, robot_sigma_mm=robot_mm, robot_sigma_deg=robot_deg)
    if candidates is None:
        cands = [(kind, E, None) for kind, E in
                 candidate_poses(sol, ds.base_T_ee, args.margin_m, box, np.random.default_rng(0))]
    else:
        cands = [("file", E, frame) for frame, E in candidates.items()]
    ranked = score_candidates(sol, preds, noise, ds.base_T_ee, cands, args.target_mm, args.target_deg)
    for i, c in enumerate(ranked, 1):  # the guide's own: next01, next02, ... best first, as `live` names them
        c.frame = c.frame or f"next{i:02d}"
    t_now, r_now = largest_sigma({c: uncertainty_report(X, sol.covariance[c])["sigma_ee_frame"]
                                  for c, X in sol.ee_T_cam.items()})
    poses = len(sol.frames)
    unchecked = f", unchecked below {MIN_CHECKED_POSES} poses" if poses < MIN_CHECKED_POSES else ""
    print(f"now: largest total sigma {t_now:.3f} mm, {r_now:.4f} deg ({poses} poses{unchecked}; target "
          f"{args.target_mm} mm, {args.target_deg} deg)")
    print(f"{'rank':>4} {'candidate':>10} {'kind':>8} {'sigma t after':>14} {'sigma r after':>14} {'points':>7}")
    rows = []
    for i, c in enumerate(ranked, 1):
        t_mm, r_deg = largest_sigma(c.sigma_after)
        if i <= args.next:
            print(f"{i:4d} {c.frame:>10} {c.kind:>8} {t_mm:11.3f} mm {r_deg:10.4f} deg {c.visible_points:7d}")
        rows.append({"frame": c.frame, "kind": c.kind, "base_T_ee": c.base_T_ee.matrix().tolist(),
                     "objective_after": c.objective_after, "objective_gain": c.gain, "sigma_after": c.sigma_after,
                     "largest_sigma_after_mm": t_mm, "largest_sigma_after_deg": r_deg,
                     "visible_points": c.visible_points})
    out = _out_dir(args)
    atomic_write_json(out / "plan.json", {"candidates_file": str(args.candidates) if args.candidates else None,
                                          "target_mm_deg": [args.target_mm, args.target_deg],
                                          "now_largest_sigma_mm_deg": [t_now, r_now], "ranking": rows})
    write_robot_poses(out / "next_poses.csv", {c.frame: c.base_T_ee for c in ranked[:args.next]}, unit)
    print(f"wrote {out / 'plan.json'}, {out / 'next_poses.csv'} (the best {min(args.next, len(ranked))}, as "
          "robot_poses.csv)")


def cmd_predict(args):
    from calib3r_graph.frontends import run_frontend
    from calib3r_graph.io.dataset import load_dataset

    ds = load_dataset(args.dataset, skip_missing=args.skip_missing)
    name = run_frontend(ds, args.frontend, args.name, progress=not args.quiet)
    print(f"wrote {ds.root / 'predictions' / name}")


def cmd_convert(args):
    from calib3r_graph.frontends.foundation import convert
    from calib3r_graph.io.dataset import load_dataset

    ds = load_dataset(args.dataset, skip_missing=args.skip_missing)
    name = convert(args.model, args.file, ds, name=args.name, order=args.order, vggt_mode=args.vggt_mode,
                   neighbours=args.neighbours)
    print(f"wrote {ds.root / 'predictions' / name}")


def cmd_compare(args):
    from calib3r_graph.errors import SolveError
    from calib3r_graph.evaluation import compare as cmp
    from calib3r_graph.evaluation import consistency
    from calib3r_graph.io.dataset import ee_T_cam_by_camera, load_dataset, load_ground_truth
    from calib3r_graph.io.output import atomic_write_json, atomic_write_text, staged_directory
    from calib3r_graph.io.predictions import load_predictions
    from calib3r_graph.solver.graph import NoiseOptions

    ds = load_dataset(args.dataset)
    methods = args.methods.split(",") if args.methods else cmp.METHODS
    unknown = set(methods) - set(cmp.METHODS)
    if unknown:
        raise InputError("--methods", f"unknown method(s) {sorted(unknown)}; choose from {cmp.METHODS}")
    preds = None
    if args.predictions or set(methods) & {"jcr-predictions", "calib3r-graph"}:
        from calib3r_graph.frontends import ensure_predictions

        try:  # as solve does: the best frontend, cached, when the dataset has no predictions
            name = ensure_predictions(ds, args.predictions, progress=not args.quiet, announce=_announce)
        except InputError:
            raise
        except Calib3rError as e:  # e.g. no images for a frontend: the pattern methods can still run
            if args.predictions:
                raise
            _announce(f"warning: no predictions for jcr-predictions and calib3r-graph ({e})")
        else:
            preds = load_predictions(ds.root, name, ds.cameras, set(ds.frames))
    noise = NoiseOptions()
    if preds is not None and "match_noise_px" in preds.info:
        noise = NoiseOptions(pixel_sigma_px=float(preds.info["match_noise_px"]))
    result = cmp.compare(ds, preds, noise, methods)
    result["predictions"] = preds.name if preds is not None else None
    gt = load_ground_truth(ds.root)
    if gt is not None:
        reference, ref_name = gt["hand_eye"], "ground truth"
    elif result["methods"].get("pattern-ba", {}).get("status") == "ok":
        reference = ee_T_cam_by_camera(result["methods"]["pattern-ba"]["cameras"])
        ref_name = "pattern-ba (no ground truth)"
    else:
        reference, ref_name = {}, None
    out = Path(args.out)
    sweep = halves = None
    against_pattern = bool(ref_name and ref_name.startswith("pattern-ba"))
    if against_pattern:
        result["in_sigmas"] = consistency.consistency(result, "pattern-ba")
    with staged_directory(out) as stage:
        if ref_name:
            from calib3r_graph.evaluation.evaluate import metric_scale_table

            table = cmp.markdown_table(result, reference, ref_name)
            scale_table = metric_scale_table(result)
            if scale_table:
                table += "\n" + scale_table
            if result.get("in_sigmas"):
                table += "\n" + consistency.sigma_table(result["in_sigmas"], "Difference to pattern-ba per ee axis, "
                                                         "in sigmas (each method's total sigma combined with "
                                                         "pattern-ba's; acceptance 3σ):")
            atomic_write_text(stage / "comparison.md", table)
            cmp.bar_plot(result, reference, stage / "comparison.png", f"{ds.root.name}: errors against {ref_name}")
            print(table)
        if args.views:
            if not ref_name:
                raise SolveError("--views needs ground truth or a pattern (pattern-ba) to measure errors against")
            views = [int(v) for v in args.views.split(",")]
            sweep = cmp.views_sweep(ds, preds, noise, views, args.repeats, methods, reference)
            atomic_write_json(stage / "views_sweep.json", sweep)
            cmp.sweep_plot(sweep, stage / "views_sweep.png", ref_name)
        if args.halves:
            halves = cmp.halves(ds, preds, noise, methods)
            halves_md = cmp.halves_table(halves)
            if halves["in_sigmas"]:
                halves_md += "\n" + consistency.sigma_table(halves["in_sigmas"], "The halves' difference per ee axis, "
                                                            "in sigmas of a difference (acceptance: 3σ):")
            if against_pattern:
                check = consistency.reference_validation(halves, "pattern-ba", args.tolerance_mm, args.tolerance_deg)
                result["reference_validation"] = check
                halves_md += "\n" + check["reason"] + "\n"
            atomic_write_json(stage / "halves.json", halves)
            atomic_write_text(stage / "halves.md", halves_md)
            print(halves_md)
        atomic_write_json(stage / "comparison.json", result)  # once, with in_sigmas and the reference check
        if not args.no_report:
            from calib3r_graph.report import compare_report_html

            atomic_write_text(stage / "report.html", compare_report_html(ds.root, result, reference, ref_name,
                                                                         sweep, halves))
    for m, r in result["methods"].items():
        print(f"{m:16s} {r['status']:40.40s} {r['seconds']:6.1f} s")
    print(f"wrote {out}/comparison.json" + (", comparison.md, comparison.png" if ref_name else "") +
          (", halves.json, halves.md" if args.halves else "") + ("" if args.no_report else ", report.html"))


def cmd_import(args):
    from calib3r_graph.importers import import_recording

    dst = Path(args.dst)
    if dst.exists() and any(dst.iterdir()) and not args.force:
        raise InputError(dst, "exists and is not empty (use --force to write into it)")
    board = None
    if args.board:
        from calib3r_graph.io.boards import parse_board

        board = parse_board(args.board)  # COLSxROWS inner corners, or charuco:/circles:/acircles: specs
    print(import_recording(args.format, args.src, dst, board, progress=not args.quiet, unit=args.unit,
                           direction=args.direction))


def cmd_evaluate(args):
    from calib3r_graph.evaluation.evaluate import evaluate
    from calib3r_graph.io.output import atomic_write_json

    report = evaluate(args.result, args.dataset)
    for cam, e in report.get("hand_eye", {}).items():
        print(f"{cam}: e_t = {e['e_t_m'] * 100:.3f} cm ({e['e_t_m'] * 1e3:.2f} mm)   "
              f"e_theta = {e['e_theta_rad']:.5f} rad ({np.degrees(e['e_theta_rad']):.3f} deg)")
    m = report.get("metric_scale")
    if m and "m_s_mm" in m:
        print(f"metric scale on the board ({m['detections']} views, {m['source']}): m_s - s = "
              f"{m['m_s_minus_s_mm']:+.3f} mm, sigma_s = {m['sigma_s_mm']:.3f} mm, delta_s = "
              f"{m['delta_s_percent']:.2f} % (s = {m['square_size_mm']:.2f} mm)")
    elif m:
        print(f"metric scale on the board: {m['status']}")
    if report.get("not_evaluated"):
        print(f"not evaluated: {report['not_evaluated']}")
    r = report.get("reconstruction")
    if r:
        print(f"reconstruction to the true surface: median {r['median_mm']:.2f} mm, 90 % {r['p90_mm']:.2f} mm "
              f"({r['points']} points)")
    atomic_write_json(Path(args.result) / "evaluation.json", report)


def _refuse_non_empty(dst: Path, force: bool):
    if dst.exists() and (not dst.is_dir() or any(dst.iterdir())) and not force:
        raise InputError(dst, "exists and is not empty (use --force to write into it)")


def cmd_import_files(args):
    from calib3r_graph.import_files import import_files

    _refuse_non_empty(Path(args.dst), args.force)
    print(import_files(args.dst, args.images, args.poses, args.pose_format, args.unit, args.intrinsics, args.board,
                       progress=not args.quiet, pose_key=args.pose_key, camera_name=args.camera_name,
                       direction=args.direction))


def cmd_import_rosbag(args):
    from calib3r_graph.io.rosbag import RosbagOptions, import_rosbag

    _refuse_non_empty(Path(args.dst), args.force)
    bounds = {k: getattr(args, k) for k in ("max_speed_mm_s", "max_speed_deg_s", "min_motion_mm", "min_motion_deg",
                                            "sync_tolerance_s") if getattr(args, k) is not None}
    opt = RosbagOptions(base_frame=args.base_frame, ee_frame=args.ee_frame, image_topics=args.image_topic,
                        depth_topics=args.depth_topic or [], camera_info_topics=args.camera_info_topic or [],
                        intrinsics=args.intrinsics or [], **bounds)
    print(import_rosbag(args.bag, args.dst, opt))


def cmd_live(args):
    from calib3r_graph.live.cli import run_live

    run_live(args, _noise_from_args)


def _add_guide_args(p):
    """The guide's options, shared by live and plan (solver/guidance.py)."""
    p.add_argument("--target-mm", type=float, default=1.0,
                   help="target of the largest total sigma (live stops there; the guide's objective is scaled by it)")
    p.add_argument("--target-deg", type=float, default=0.1, help="... and this")
    p.add_argument("--next", type=int, default=5, help="how many next poses to propose (next_poses.csv)")
    p.add_argument("--margin-m", type=float, default=0.05, help="grow the visited region by this for the proposals")
    p.add_argument("--box", help="x0,y0,z0,x1,y1,z1: propose flange positions inside this box (base frame, m)")


def _add_live_args(p):
    p.add_argument("dataset", help="dataset folder (calib3r-dataset/1): its cameras, and the frames as they come")
    mode = p.add_mutually_exclusive_group(required=True)
    mode.add_argument("--replay", choices=["recorded", "guided", "random"], help="replay the recording frame by frame")
    mode.add_argument("--watch", action="store_true", help="wait for the frames a capture script adds")
    p.add_argument("--out", required=True, help="output folder: calibration.json, next_poses.csv, live.jsonl")
    p.add_argument("--seed", type=int, default=0, help="--replay random: the permutation's seed; --replay guided: above 0, "
                   "start from a seeded random frame instead of the first")
    _add_guide_args(p)
    p.add_argument("--predictions", help="use DATASET/predictions/NAME (default: the only one; none: the pairwise "
                                         "frontend on the images)")
    p.add_argument("--resume", action="store_true", help="--watch: continue a killed session from OUT/live.jsonl")
    p.add_argument("--poll-s", type=float, default=1.0, help="--watch: seconds between looks at the folder")
    p.add_argument("--idle-s", type=float, default=None, help="--watch: end after this long without a new frame")
    w = p.add_argument_group("--watch: robot poses from any pose file import files reads (default: the dataset's "
                             "robot_poses.csv); frame id = the pose's number, 0007: images/<camera>/0007.png")
    w.add_argument("--poses", help="a pose file (one pose per line or entry), or a folder or glob of one file per "
                                   "frame (.txt, .csv, .npy, .json, .yaml)")
    w.add_argument("--pose-format", help="as import files: matrix, xyz-quat-xyzw, xyz-quat-wxyz, xyz-rotvec, "
                                         "xyz-euler:ORDER:deg|rad, visp (default with --pose-key: matrix)")
    w.add_argument("--pose-key", help="the JSON/YAML entry that holds each pose, dots for nested keys")
    w.add_argument("--unit", choices=["m", "mm"], help="the poses' translation unit (default: dataset.yaml's)")
    w.add_argument("--direction", choices=["base_T_ee", "ee_T_base"], default="base_T_ee",
                   help="what the poses are (default base_T_ee)")
    _add_noise_args(p)
    p.set_defaults(func=cmd_live)


def cmd_export(args):
    from calib3r_graph.io.export import export
    from calib3r_graph.io.output import atomic_write_text

    text = export(args.result, args.format, args.parent, args.child, args.camera, args.child_convention)
    if args.out:
        atomic_write_text(Path(args.out), text)
        print(f"wrote {args.out}", file=sys.stderr)
    else:
        print(text, end="")


def _add_import_files_args(p):
    # Parsers are built on every run: the modules behind these commands are imported only in cmd_*.
    p.add_argument("dst", help="output dataset folder")
    p.add_argument("--images", action="append", required=True,
                   help="a folder or glob of one camera's images; repeat per camera (cam0, cam1, ...)")
    p.add_argument("--poses", required=True, help="a pose file (one pose per line), or a folder or glob of one "
                                                  "file per frame (.txt, .npy, .json, .yaml)")
    p.add_argument("--pose-format",
                   help="matrix, xyz-quat-xyzw, xyz-quat-wxyz, xyz-rotvec, xyz-euler:ORDER:deg|rad (KUKA: "
                        "xyz-euler:zyx:deg), xyz-euler:fixed-ORDER:deg|rad (ROS rpy: fixed-xyz), visp "
                        "(required, except with --pose-key: then matrix by default)")
    p.add_argument("--pose-key", help="the JSON/YAML entry that holds each pose, dots for nested keys (Franka's "
                                      "data.json: O_T_EE, row- or column-major, found from the numbers)")
    p.add_argument("--unit", choices=["m", "mm"], help="translation unit of the poses (default m; with a board the "
                                                       "images decide unless it is given)")
    _add_convention_args(p, unit=False)
    p.add_argument("--intrinsics", action="append", help="ROS camera_info YAML, OpenCV FileStorage YAML/XML, "
                                                         "Kalibr camchain, ViSP camera.xml or .npz (K, dist); "
                                                         "repeat per camera; with --board too, the board checks "
                                                         "the poses' direction and unit")
    p.add_argument("--camera-name", help="which camera of a ViSP camera.xml that holds several")
    p.add_argument("--board", help="board in the images: COLSxROWS:SQUARE_M (inner corners), "
                                   "charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT], circles:COLSxROWS:SPACING_M, "
                                   "acircles:COLSxROWS:SPACING_M")
    p.add_argument("--force", action="store_true", help="write into a non-empty folder")
    p.set_defaults(func=cmd_import_files)


def _add_convention_args(p, unit=True):
    # The pose convention: the board's motion decides what is not given; what is given is still checked.
    if unit:
        p.add_argument("--unit", choices=["m", "mm"], help="force the poses' translation unit (default: the "
                                                           "images decide)")
    p.add_argument("--direction", choices=["base_T_ee", "ee_T_base"],
                   help="force the poses' direction (default base_T_ee; with a board the images decide unless it is "
                        "given; a forced convention that does not fit is still refused)")


def _add_import_rosbag_args(p):
    p.add_argument("bag", help="a ROS 1 .bag file, or a ROS 2 bag folder (sqlite3 or MCAP)")
    p.add_argument("dst", help="output dataset folder")
    p.add_argument("--base-frame", required=True, help="the robot's base frame in /tf (e.g. base_link)")
    p.add_argument("--ee-frame", required=True, help="the flange frame the camera is mounted on (e.g. tool0)")
    p.add_argument("--image-topic", action="append", required=True,
                   help="Image or CompressedImage topic; repeat per camera (cam0, cam1, ...)")
    p.add_argument("--depth-topic", action="append", help="registered depth (16UC1 mm or 32FC1 m), per camera")
    p.add_argument("--camera-info-topic", action="append",
                   help="CameraInfo topic per camera (default: camera_info beside the image topic)")
    p.add_argument("--intrinsics", action="append", help="an intrinsics file per camera instead of camera_info")
    g = p.add_argument_group("frame selection")
    g.add_argument("--max-speed-mm-s", type=float, help="skip images taken while the flange moves faster than "
                                                        "this within 0.1 s (default 10)")
    g.add_argument("--max-speed-deg-s", type=float, help="the same for rotation (default 2)")
    g.add_argument("--min-motion-mm", type=float, help="skip images whose flange pose is within this and "
                                                       "--min-motion-deg of the last kept one (default 5)")
    g.add_argument("--min-motion-deg", type=float, help="(default 1)")
    g.add_argument("--sync-tolerance-s", type=float, help="largest stamp difference between a frame's images of "
                                                          "different cameras, and of depth (default 0.05)")
    p.add_argument("--force", action="store_true", help="write into a non-empty folder")
    p.set_defaults(func=cmd_import_rosbag)


EXPORT_FORMATS = ("urdf", "xacro", "ros2-launch", "ros1-launch", "tf-yaml", "easy-handeye")  # export.FORMATS


def _add_export_args(p):
    p.add_argument("result", help="a folder written by solve (calibration.json)")
    p.add_argument("--format", choices=EXPORT_FORMATS, required=True)
    p.add_argument("--parent", required=True, help="the flange link the camera is mounted on (e.g. tool0)")
    p.add_argument("--child", required=True, help="the camera frame to create (e.g. camera_color_optical_frame)")
    p.add_argument("--camera", help="which camera of the result (default: the only one)")
    p.add_argument("--child-convention", choices=["optical", "camera_link"], default="optical",
                   help="optical: z forward, x right, y down (REP 103/105, default); camera_link: x forward, "
                        "y left, z up")
    p.add_argument("--out", help="write to this file (atomically) instead of stdout")
    p.set_defaults(func=cmd_export)


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"{n}: must be 1 or more")
    return n


def _add_solve_args(s):
    s.add_argument("dataset", help="dataset folder (calib3r-dataset/1)")
    s.add_argument("--out", help="output folder (default: results/<dataset name>)")
    s.add_argument("--predictions", help="name under DATASET/predictions/ (default: the only one, or 'sim')")
    s.add_argument("--skip-missing", action="store_true", help="drop frames without a robot pose, with a warning")
    g = s.add_argument_group("solver")
    g.add_argument("--max-matches-per-pair", type=int, default=2000, help="confidence-weighted subsample")
    g.add_argument("--irls-rounds", type=int, default=2, help="robust re-weighting rounds after the first solve")
    g.add_argument("--max-iterations", type=int, default=50, help="LM iterations per round")
    g.add_argument("--init", choices=["predictions", "colmap"], default="predictions",
                   help="visual initialisation: pairwise Sim(3) + spanning tree, or COLMAP's poses "
                        "(predictions made by the colmap frontend)")
    g.add_argument("--jackknife", choices=["auto", "always", "never"], default="auto",
                   help="leave-one-pose-out solves (n extra) whose spread the total covariance covers; "
                        "auto: below 15 robot poses, where the robot's error field cannot be measured "
                        "(default: auto)")
    g.add_argument("--jackknife-method", choices=["resolve", "linearised"], default=None,
                   help="resolve: n re-solves, robust re-weighting and noise calibration included; "
                        "linearised: one downdate of the solved graph per pose (a fraction of a second, "
                        "robust weights held; docs/uncertainty.md) (default: resolve)")
    g.add_argument("--jobs", type=_positive_int, default=None, metavar="N",
                   help="processes for the re-solving jackknife's independent solves (the same numbers at any N; "
                        "default: every CPU)")
    g.add_argument("--reprojection", action="store_true",
                   help="add 2D reprojection factors (double-counts match noise; off by default)")
    g.add_argument("--intrinsics-sigma-px", metavar="F,C",
                   help="1-sigma of the focal lengths and of the principal point (px), propagated into the total "
                        "sigma, e.g. for factory intrinsics; replaces dataset.yaml's params_sigma (default: "
                        "params_sigma where dataset.yaml has it, else the camera model is not in the sigma)")
    _add_noise_args(s)


_DESCRIPTION = """\
Eye-in-hand hand-eye calibration: finds ee_T_cam, the transform from the robot's flange to the
camera, for one camera or every camera of a rig, from the flange poses and the images taken at
them. No calibration pattern is needed. The hand-eye, the metric scale and a metric 3D
reconstruction are solved jointly in one factor graph, and every result comes with its
1-sigma per axis in mm and degrees. compare runs OpenCV's hand-eye solvers beside it."""

_EPILOG = """\
from your robot's files to a URDF:
  calib3r-graph import files mycell --images shots/ --poses poses.txt --pose-format FMT --board SPEC
  calib3r-graph solve mycell --out mycell_result        (then read the summary and its warnings)
  calib3r-graph export mycell_result --format urdf --parent tool0 --child camera_optical_frame

'calib3r-graph COMMAND --help' lists a command's options; README.md and docs/ explain them."""


def build_parser():
    p = argparse.ArgumentParser(prog="calib3r-graph", description=_DESCRIPTION, epilog=_EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks and debug logging")
    p.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("solve", help="joint hand-eye calibration and metric reconstruction of a dataset")
    _add_solve_args(s)
    s.add_argument("--no-cloud", action="store_true", help="skip reconstruction.ply")
    s.add_argument("--no-report", action="store_true", help="skip report.html")
    s.add_argument("--dense", action="store_true", help="also run the dense reconstruction (dense.ply, mesh.ply)")
    _add_dense_args(s)
    s.set_defaults(func=cmd_solve)

    pl = sub.add_parser("plan", help="the next robot poses to record, ranked by the total sigma expected after each")
    _add_solve_args(pl)
    pl.add_argument("--candidates", help="CSV like robot_poses.csv (frame,x,y,z,qx,qy,qz,qw): rank these "
                                         "(default: the live guide's candidates, generated from the solution)")
    _add_guide_args(pl)
    pl.set_defaults(func=cmd_plan)

    pr = sub.add_parser("predict", help="make predictions/<name>/ from the dataset's images (and depth)")
    pr.add_argument("dataset", help="dataset folder (calib3r-dataset/1)")
    pr.add_argument("--frontend", choices=["rgbd", "colmap", "pairwise"], required=True)
    pr.add_argument("--name", help="predictions name (default: the frontend's name)")
    pr.add_argument("--skip-missing", action="store_true", help="drop frames without a robot pose, with a warning")
    pr.set_defaults(func=cmd_predict)

    cv = sub.add_parser("convert", help="turn a VGGT / DUSt3R / MASt3R export into predictions/<name>/")
    cv.add_argument("model", choices=["vggt", "dust3r", "mast3r"])
    cv.add_argument("file", help="the .npz saved where the model ran")
    cv.add_argument("dataset", help="dataset folder (calib3r-dataset/1) the images came from")
    cv.add_argument("--name", help="predictions name (default: the model's name)")
    cv.add_argument("--order", help="text file: the image paths in the order given to the model "
                                     "(needed when the npz has no image_names)")
    cv.add_argument("--vggt-mode", choices=["crop", "pad"], default="crop",
                    help="load_and_preprocess_images mode used for VGGT")
    cv.add_argument("--neighbours", type=int, default=5, help="co-visibility: top-k neighbours per view")
    cv.add_argument("--skip-missing", action="store_true", help=argparse.SUPPRESS)
    cv.set_defaults(func=cmd_convert)

    m = sub.add_parser("simulate", help="render a synthetic dataset with ground truth and predictions")
    m.add_argument("out", help="output dataset folder")
    m.add_argument("--seed", type=int, default=0)
    m.add_argument("--frames", type=int, default=12)
    m.add_argument("--cameras", type=int, default=1, help="1-3 cameras on the flange")
    m.add_argument("--pattern", action="store_true", help="put a 9x6 checkerboard (30 mm) on the table")
    m.add_argument("--no-images", action="store_true", help="predictions only (fast)")
    m.add_argument("--width", type=int, default=640)
    m.add_argument("--height", type=int, default=480)
    m.add_argument("--unit", choices=["m", "mm"], default="m", help="robot translation unit in the csv")
    m.add_argument("--depth-distortion", type=float, default=0.015, help="peak smooth relative depth error")
    m.add_argument("--outlier-fraction", type=float, default=0.04)
    m.add_argument("--matches-per-pair", type=int, default=2000)
    m.add_argument("--prediction-downsample", type=int, default=2, help="network grid = image / this")
    m.add_argument("--robot-noise-mm", type=float, default=0.2)
    m.add_argument("--robot-noise-deg", type=float, default=0.02)
    m.add_argument("--trajectory", choices=["hemisphere", "orbit"], default="hemisphere",
                   help="orbit: one distance, looking at the table's centre, like rwhe_kuka_2 (scale unobservable)")
    m.add_argument("--force", action="store_true", help="write into a non-empty folder")
    m.set_defaults(func=cmd_simulate)
    c = sub.add_parser("compare", help="run every calibration method on the same data, timed, with a table")
    c.add_argument("dataset", help="dataset folder (calib3r-dataset/1)")
    c.add_argument("--out", required=True, help="output folder: comparison.json, comparison.md, PNG plots")
    c.add_argument("--predictions", help="predictions for the prediction-based methods")
    c.add_argument("--methods", help="comma-separated subset of the methods (default: all)")
    c.add_argument("--views", help="robustness sweep over the number of poses, e.g. 5,7,9,...,25")
    c.add_argument("--repeats", type=int, default=3, help="random subsets per number of poses")
    c.add_argument("--halves", action="store_true",
                   help="also solve every method on each half of the frames and report how far apart the two are")
    c.add_argument("--tolerance-mm", type=float, default=5.0,
                   help="with --halves: the tolerance the pattern reference must repeat 3x better than (default 5)")
    c.add_argument("--tolerance-deg", type=float, default=0.3, help="the same in rotation (default 0.3)")
    c.add_argument("--no-report", action="store_true", help="skip report.html")
    c.set_defaults(func=cmd_compare)

    im_all = sub.add_parser("import", help="convert a recording (rwhe, tabb, your files, a ROS bag) into a dataset")
    im_sub = im_all.add_subparsers(dest="format", required=True)
    for fmt in ("rwhe", "tabb"):
        im = im_sub.add_parser(fmt, help=f"the public {fmt} recording format")
        im.add_argument("src", help="the recording's folder, as published")
        im.add_argument("dst", help="output dataset folder")
        im.add_argument("--board", help="chessboard inner corners COLSxROWS (rwhe needs it; tabb reads its file), "
                                        "or charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT], circles:/acircles:COLSxROWS:"
                                        "SPACING_M")
        im.add_argument("--force", action="store_true", help="write into a non-empty folder")
        _add_convention_args(im)
        im.set_defaults(func=cmd_import)
    _add_import_files_args(im_sub.add_parser("files", help="images per camera and a robot pose file"))
    _add_import_rosbag_args(im_sub.add_parser("rosbag", help="a ROS 1 .bag or ROS 2 bag (sqlite3, MCAP)"))

    ex = sub.add_parser("export", help="write a solve result as URDF, xacro, ROS launch, tf YAML or easy_handeye")
    _add_export_args(ex)

    rc = sub.add_parser("reconstruct", help="dense cloud and mesh of a solve result, in the robot's base frame")
    rc.add_argument("result", help="folder written by solve (calibration.json, trajectory.csv); never modified "
                                   "except for dense.ply, mesh.ply, dense.json, summary.txt's dense lines and "
                                   "report.html")
    rc.add_argument("dataset", help="the dataset folder that was solved")
    rc.add_argument("--no-report", action="store_true", help="leave report.html as it is")
    _add_dense_args(rc)
    rc.set_defaults(func=cmd_reconstruct)

    e = sub.add_parser("evaluate", help="compare a solve result with the dataset's ground truth")
    e.add_argument("result", help="folder written by solve")
    e.add_argument("dataset", help="dataset folder with ground_truth.yaml")
    e.set_defaults(func=cmd_evaluate)
    _add_live_args(sub.add_parser("live", help="live, guided calibration: update per frame, propose the next poses"))
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    level = logging.DEBUG if args.debug else logging.WARNING if args.quiet else logging.INFO
    logging.basicConfig(level=level, format="%(levelname)s: %(message)s", stream=sys.stderr)
    try:
        args.func(args)
    except Calib3rError as e:
        if args.debug:  # the traceback, then the same exit code as without --debug
            traceback.print_exc()
        print(f"calib3r-graph: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("calib3r-graph: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # a library's failure or a bug: one line, the traceback with --debug
        if args.debug:
            traceback.print_exc()
        from calib3r_graph.errors import library_error

        described = library_error(e)
        hint = "" if args.debug else " (run with --debug for the details)"
        if described is not None:
            print(f"calib3r-graph: error: {described[0]}{hint}", file=sys.stderr)
            return described[1]
        first = next((line for line in str(e).splitlines() if line.strip()), "")
        print(f"calib3r-graph: internal error: {type(e).__name__}: {first}"
              + ("" if args.debug else " (run with --debug for the traceback)"), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
