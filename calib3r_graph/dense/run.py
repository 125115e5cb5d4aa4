"""``calib3r-graph reconstruct RESULT_DIR DATASET`` and ``solve --dense``: per-view dense depth, the fused
cloud and mesh, the cross-view disagreement check, and their figures (dense.json)."""

import logging
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

import calib3r_graph.dense.check as check
import calib3r_graph.dense.stereo as stereo
from calib3r_graph.dense.fuse import Fusion, write_dense_ply, write_mesh
from calib3r_graph.dense.views import SolveResult, dense_views, load_images, read_result
from calib3r_graph.errors import InputError, SolveError
from calib3r_graph.io.output import atomic_write_json, atomic_write_text

log = logging.getLogger(__name__)

SOURCES = ("auto", "stereo", "depth", "predictions")
# A view whose depth covers less than this share of its grid has not been matched (a blank or blurred
# image, a pose that disagrees with the image): 1 % of a 960x600 grid is 5800 pixels.
MIN_COVERAGE = 0.01
# Predictions count as dense depth (a sensor's or a foundation model's) when this share of a view's grid
# has depth; the pairwise and colmap frontends' triangulated depth covers well under 5 %.
DENSE_PREDICTIONS = 0.5
# The check compares each view with the views that overlap it most, whatever their baseline: the more
# their orientations differ, the more a wrong ee_T_cam separates their surfaces (R_ee_a dt vs R_ee_b dt).
CHECK_PAIRS = 8
# A view whose stereo depth lies, under the solved poses, more than this many voxels from the surfaces
# of the views that overlap it (the median of its pairs' median distances) is skipped: every kept depth's
# own noise is below one voxel (stereo.consistent_depth drops the rest), so two right views' surfaces
# are sqrt(2) voxels apart at most in sigma, a median distance under one voxel. Beyond two, the view's
# pose disagrees with its image: on the simulator a view moved by 5 mm lies 5.7 mm off (one moved by
# 10 cm no longer matches at all); on rwhe_kuka_1 the worst right view scores well below (docs/dense.md).
INCONSISTENT_VOXELS = 2.0


@dataclass
class DenseOptions:
    voxel_mm: float = 2.0
    max_views: int | None = None
    max_side: int = 960  # long side of the working grid, px (1928x1208 -> 960x601)
    # Stereo partners per view. The fusion keeps a surface point only where two views' depth maps reach it
    # (fuse.WEIGHT_THRESHOLD), so each view's map must cover what its neighbours' maps cover: with 4
    # partners the simulator's fused cloud covered 78 % of the surface two views see, with 6 82 %, for
    # 1.37x the CPU time per view (1.7 -> 2.3 s at 960x720).
    neighbours: int = 6
    source: str = "auto"
    progress: bool = True


@dataclass
class DenseState:
    """Each view's depth and what the fusion and the check need."""

    views: dict  # view -> DenseView
    depths: dict = field(default_factory=dict)  # view -> (h, w) float32 metres, NaN where none
    confs: dict = field(default_factory=dict)
    rays: dict = field(default_factory=dict)
    neighbours: dict = field(default_factory=dict)  # the stereo partners of each view
    check_pairs: dict = field(default_factory=dict)  # view -> the views it is compared with by the check
    skipped: dict = field(default_factory=dict)  # view -> reason
    source: str = "stereo"
    depth_seconds: float = 0.0
    depth_cpu_seconds: float = 0.0  # CPU time of all this process's threads (a shared machine's wall time varies)


def _subset(views: dict, n: int | None) -> dict:
    """``n`` views spread evenly over the recording (all when n is None or not smaller)."""
    if not n or n >= len(views):
        return views
    keys = list(views)
    return {keys[i]: views[keys[i]] for i in np.unique(np.linspace(0, len(keys) - 1, n).round().astype(int))}


def _sparse_points(result: SolveResult, views: dict, max_points=20000) -> np.ndarray:
    """The solve's reconstruction.ply (subsampled) to find each view's depth range and overlap, or, where
    it is absent, points where the views' optical axes meet."""
    path = result.dir / "reconstruction.ply"
    if path.is_file():
        import open3d as o3d

        pts = np.asarray(o3d.io.read_point_cloud(str(path)).points)
        if len(pts) >= 100:
            if len(pts) > max_points:
                pts = pts[np.random.default_rng(0).choice(len(pts), max_points, replace=False)]
            return pts
    return stereo.look_at_points(views)


def _source(ds, result: SolveResult, requested: str):
    """Which per-view depth to fuse: the sensor's (depth/), a foundation model's dense predictions (with
    the solve's depth scale and correction from views.npz), or stereo from the images."""
    if requested in ("auto", "depth") and ds.has_depth():
        return "depth", None
    if requested == "depth":
        raise InputError(ds.root / "depth", "missing: --source depth needs the dataset's sensor depth")
    if requested in ("auto", "predictions") and result.predictions:
        from calib3r_graph.io.predictions import load_predictions
        from calib3r_graph.io.results import read_views

        pdir = ds.root / "predictions" / result.predictions
        if pdir.is_dir() and (result.dir / "views.npz").is_file():
            preds = load_predictions(ds.root, result.predictions, ds.cameras, set(ds.frames), skip_missing=True)
            cover = [np.mean(vp.depth > 0) for vp in preds.views.values()]
            if cover and np.median(cover) >= DENSE_PREDICTIONS:
                return "predictions", (preds, read_views(result.dir / "views.npz"))
    if requested == "predictions":
        raise InputError(ds.root / "predictions", f"no dense predictions '{result.predictions}' with the solve's "
                                                  "views.npz (--source predictions)")
    return "stereo", None


def _given_depth(state: DenseState, ds, kind: str, extra, progress: bool):
    """Sensor or prediction depth, metric, on each view's grid."""
    from calib3r_graph.io.results import metric_depth

    for v, dv in tqdm(state.views.items(), desc="dense depth", disable=None if progress else True, leave=False):
        why = load_images(dv)
        if kind == "depth":
            path = ds.depth_path(dv.camera, dv.frame)
            raw = None if path is None else cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if raw is None:
                state.skipped[v] = "no readable depth map"
                continue
            cam = ds.cameras[dv.camera]
            d = raw.astype(np.float32) * float(cam.depth_scale or 1e-3)
            mx, my = cv2.initUndistortRectifyMap(cam.K, cam.dist, None, dv.K, dv.size, cv2.CV_32FC1)
            d = cv2.remap(d, mx, my, cv2.INTER_NEAREST)
            conf = (d > 0).astype(np.float32)
        else:
            preds, states = extra
            vp = preds.views.get(v)
            if vp is None or v not in states.depth_scale:
                state.skipped[v] = "no prediction for this view"
                continue
            h, w = vp.depth.shape
            dv.K, dv.size = vp.K, (w, h)
            uv = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2).astype(float)
            d = metric_depth(vp, states.depth_scale[v], states.depth_correction[v], uv).reshape(h, w)
            d = np.where((vp.depth > 0) & (vp.conf > 0), d, 0).astype(np.float32)
            conf = (vp.conf / max(float(vp.conf.max()), 1e-9)).astype(np.float32)
            if why is None:
                dv.rgb = cv2.resize(dv.rgb, (w, h), interpolation=cv2.INTER_AREA)
        if why is not None:
            dv.rgb = np.full((dv.size[1], dv.size[0], 3), 160, np.uint8)
        state.depths[v] = np.where(d > 0, d, np.nan).astype(np.float32)
        state.confs[v] = conf
        state.rays[v] = stereo.pixel_rays(dv.K, dv.size)


def _stereo_depth(state: DenseState, result: SolveResult, opt: DenseOptions):
    views = state.views
    for v, dv in list(views.items()):
        why = load_images(dv)
        if why:
            state.skipped[v] = why
    usable = {v: dv for v, dv in views.items() if v not in state.skipped}
    ranges, seen = stereo.depth_ranges(usable, _sparse_points(result, usable))
    state.neighbours = stereo.choose_neighbours(usable, ranges, seen, opt.neighbours)
    state.check_pairs = {v: _overlap_neighbours(v, seen, CHECK_PAIRS) for v in usable}
    for v, dv in tqdm(usable.items(), desc="dense depth (SGBM)", disable=None if opt.progress else True, leave=False):
        nbrs = state.neighbours.get(v, [])
        if len(nbrs) < 2:
            state.skipped[v] = (f"{len(nbrs)} neighbour view(s) with overlap and a usable baseline (2 needed)"
                                if v in ranges else "sees none of the solve's scene points")
            continue
        rays = stereo.pixel_rays(dv.K, dv.size)
        est = [e for u in nbrs
               if (e := stereo.pair_depth(dv, usable[u], ranges[v], rays, opt.voxel_mm * 1e-3)) is not None]
        if len(est) < 2:
            state.skipped[v] = "the pairs with its neighbours could not be rectified"
            continue
        depth, conf = stereo.consistent_depth(est, max_sigma_m=opt.voxel_mm * 1e-3)
        cover = float(np.isfinite(depth).mean())
        if cover < MIN_COVERAGE:
            state.skipped[v] = (f"matching failed: {100 * cover:.2f} % of the pixels have a depth that two "
                                f"neighbour views agree on")
            continue
        state.depths[v], state.confs[v], state.rays[v] = depth, conf, rays


def compute_depths(ds, result: SolveResult, opt: DenseOptions, ee_T_cam: dict | None = None) -> DenseState:
    if opt.source not in SOURCES:
        raise InputError("--source", f"must be one of {', '.join(SOURCES)}")
    views = _subset(dense_views(ds, result, opt.max_side, ee_T_cam), opt.max_views)
    if not views:
        raise InputError(result.dir / "trajectory.csv", f"no solved view belongs to the dataset {ds.root}")
    state = DenseState(views)
    state.source, extra = _source(ds, result, opt.source)
    t0, cpu0 = time.perf_counter(), _cpu_seconds()
    if state.source == "stereo":
        _stereo_depth(state, result, opt)
        _drop_inconsistent(state, opt.voxel_mm)
    else:
        _given_depth(state, ds, state.source, extra, opt.progress)
        ranges, seen = stereo.depth_ranges(views, _sparse_points(result, views))
        state.check_pairs = {v: _overlap_neighbours(v, seen, CHECK_PAIRS) for v in views}
    state.depth_seconds = time.perf_counter() - t0
    state.depth_cpu_seconds = _cpu_seconds() - cpu0
    for v, why in state.skipped.items():
        log.warning("dense: %s skipped: %s", v, why)
    if not state.depths:
        raise SolveError(f"dense: no view gave a depth map ({len(state.skipped)} skipped; first: "
                         f"{next(iter(state.skipped.items()), ('', ''))[0]}: {next(iter(state.skipped.values()), '')}; "
                         "where the scene is far, one pair's depth noise can exceed the voxel: try a larger "
                         "--voxel-mm)")
    return state


def _drop_inconsistent(state: DenseState, voxel_mm: float):
    """Skips the views whose depth disagrees with the views around it under the solved poses, worst
    first: a wrong view spoils each of its pairs, a right one only its pair with the wrong view."""
    poses = {v: dv.base_T_cam for v, dv in state.views.items()}
    pairs = check.disagreement(state.depths, state.rays, state.views, state.check_pairs, poses,
                               per_pair=True)["pair_median_mm"]
    while pairs:
        by_view = {}
        for (a, b), mm in pairs.items():
            by_view.setdefault(a, []).append(mm)
            by_view.setdefault(b, []).append(mm)
        # with one pair only, which of the two views is wrong cannot be told
        scored = [(float(np.median(m)), v) for v, m in by_view.items() if len(m) >= 2]
        score, v = max(scored) if scored else (0.0, None)
        if score <= INCONSISTENT_VOXELS * voxel_mm:
            return
        state.skipped[v] = (f"its depth lies {score:.1f} mm from the surfaces of the views that overlap it "
                            f"under the solved poses (more than {INCONSISTENT_VOXELS:g} voxels): a pose that "
                            "disagrees with the image")
        for d in (state.depths, state.confs, state.rays):
            d.pop(v, None)
        pairs = {ab: mm for ab, mm in pairs.items() if v not in ab}


def _cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _overlap_neighbours(v, seen: dict, n: int) -> list:
    if not seen[v].any():
        return []
    scores = sorted(((float((seen[v] & s).sum() / seen[v].sum()), u) for u, s in seen.items() if u != v),
                    reverse=True)
    return [u for sc, u in scores[:n] if sc >= 0.25]


def fuse(state: DenseState, voxel_m: float, progress: bool = True):
    fusion = Fusion(voxel_m)
    for v in tqdm(list(state.depths), desc="TSDF fusion", disable=None if progress else True, leave=False):
        dv = state.views[v]
        fusion.add(state.depths[v], state.confs[v], dv.rgb, dv.K, dv.base_T_cam, state.rays[v])
    return fusion


def reconstruct(ds, result: SolveResult, opt: DenseOptions, out_dir) -> dict:
    """Dense depth, fusion, check; writes dense.ply, mesh.ply and dense.json into ``out_dir``; returns the
    figures (what dense.json holds)."""
    return reconstruct_with_state(ds, result, opt, out_dir)[0]


def reconstruct_with_state(ds, result: SolveResult, opt: DenseOptions, out_dir) -> tuple[dict, DenseState]:
    """:func:`reconstruct`, also returning the views' depth (for bench/dense.py's sweep of the check)."""
    t0 = time.perf_counter()
    state = compute_depths(ds, result, opt)
    t1 = time.perf_counter()
    fusion = fuse(state, opt.voxel_mm * 1e-3, opt.progress)
    pts, nrm, col, conf, mesh = fusion.extract()
    t2 = time.perf_counter()
    if len(pts) == 0:
        raise SolveError("dense: the fused volume holds no surface")
    disagreement = check.disagreement(state.depths, state.rays, state.views, state.check_pairs)
    out_dir = Path(out_dir)
    write_dense_ply(out_dir / "dense.ply", pts, nrm, col, conf)
    write_mesh(out_dir / "mesh.ply", mesh)
    coverage = [float(np.isfinite(d).mean()) for d in state.depths.values()]
    figures = {"format": "calib3r-dense/1", "source": state.source, "voxel_mm": opt.voxel_mm,
               "working_grid": [int(x) for x in next(iter(state.views.values())).size],
               "views_used": len(state.depths),
               "views_skipped": [{"view": v, "reason": r} for v, r in sorted(state.skipped.items())],
               "points_before_voxel": int(fusion.points_before_voxel), "points": int(len(pts)),
               "mesh_vertices": int(len(mesh.vertices)), "mesh_triangles": int(len(mesh.triangles)),
               "coverage_mean": float(np.mean(coverage)),
               "seconds_per_view": state.depth_seconds / max(len(state.views), 1),
               "cpu_seconds_per_view": state.depth_cpu_seconds / max(len(state.views), 1),
               "seconds": {"depth": t1 - t0, "fusion": t2 - t1, "total": time.perf_counter() - t0},
               "peak_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
               "disagreement": {**disagreement, "poses": "robot chain base_T_ee . ee_T_cam"}}
    atomic_write_json(out_dir / "dense.json", figures)
    return figures, state


def summary_lines(f: dict) -> str:
    d = f["disagreement"]
    dis = (f"cross-view surface disagreement under base_T_ee·ee_T_cam: median {d['median_mm']:.2f} mm, "
           f"90 % {d['p90_mm']:.2f} mm ({d['pairs']} view pairs)" if d["median_mm"] is not None
           else "cross-view surface disagreement: no overlapping view pairs")
    skipped = f", {len(f['views_skipped'])} skipped" if f["views_skipped"] else ""
    named = "".join(f"  dense: skipped {s['view']} ({s['reason']})\n" for s in f["views_skipped"])
    return (f"  dense ({f['source']}): {f['views_used']} views{skipped}, {f['points_before_voxel']} points before "
            f"the {f['voxel_mm']:g} mm voxel grid, {f['points']} in dense.ply, {f['seconds_per_view']:.1f} s per "
            f"view\n  dense: {dis}\n" + named)


def reconstruct_result(result_dir, dataset_dir, opt: DenseOptions) -> dict:
    """``reconstruct``: reads a finished solve, writes dense.ply, mesh.ply and dense.json beside it and the
    figures into summary.txt; calibration.json is never touched."""
    from calib3r_graph.io.dataset import load_dataset

    result = read_result(result_dir)
    ds = load_dataset(dataset_dir, skip_missing=True)
    figures = reconstruct(ds, result, opt, result.dir)
    summary = result.dir / "summary.txt"
    if summary.is_file():  # replace the lines of an earlier reconstruct
        kept = [line for line in summary.read_text().splitlines(keepends=True) if not line.startswith("  dense")]
        atomic_write_text(summary, "".join(kept) + summary_lines(figures))
    return figures
