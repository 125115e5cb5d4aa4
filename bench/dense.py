"""The dense reconstruction (calib3r_graph.dense, docs/dense.md) on the simulator and on every recording
in ../shared/real, from RGB alone (SGBM stereo on the solved poses).

Per run: points (before the voxel grid and in dense.ply), coverage, time per view, peak memory.
- Simulator: distance of the dense points to the true surface (median, p90; also for the points 0.4-0.6 m
  from the nearest camera) and the share of the surface that two or more views see which the cloud covers.
- Real recordings: the board's flatness on the dense cloud (RMS to a fitted plane), that plane's distance
  along its normal to the board plane of the pattern-ba reference (pattern-ba's ee_T_cam composed with
  each view's PnP board pose, averaged), split into the two hand-eyes' difference along the normal and
  the dense depth's own offset (to the board plane through our solved poses), beside the sigma of each
  hand-eye along the normal; and the board's square size measured on the dense cloud (the
  detected corners' rays through the solved poses, intersected with the dense board plane) against the
  printed one; and the cross-view disagreement under ee_T_cam moved by 1, 2, 5 mm or turned by 0.1, 0.2,
  0.5 degrees about each ee axis.

Each run is a child process (its own peak memory). Writes bench/results/dense.md, dense.json and
dense_<recording>.png.

    .venv/bin/python bench/dense.py [--work /tmp/calib3r-dense] [--real ../shared/real]
                                    [--recordings rwhe_kuka_1,...] [--skip-sim] [--result-of NAME=DIR ...]
"""

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

BOARDS = {"rwhe_kuka_1": "28x17", "rwhe_kuka_2": "24x17"}  # inner corners, from each recording's README
SWEEP_MM, SWEEP_DEG = (1.0, 2.0, 5.0), (0.1, 0.2, 0.5)
SIM = dict(seed=7, frames=24, width=960, height=720)
# The voxel starts at 2 mm for every run. Where the dense step keeps no view at that size (it drops
# depths noisier than the voxel: tabb_ds1's 640x480 views see its board 3.8 m away, where one pair's
# depth noise is ~4 mm, z^2 0.25 px / fB with fB ~ 900 px m), the same rule for every run doubles it,
# up to VOXEL_MAX_MM: no per-recording constant.
VOXEL_START_MM, VOXEL_MAX_MM = 2.0, 16.0


def _cli(*args):
    from calib3r_graph.cli import main

    rc = main(["-q", *map(str, args)])
    if rc != 0:
        raise SystemExit(f"calib3r-graph {' '.join(map(str, args))} failed ({rc})")


def prepare(name: str, work: Path, real: Path):
    """(dataset, result) folders: imported and solved unless already there."""
    ds, res = work / name, work / f"{name}_res"
    if name == "sim":
        if not (ds / "dataset.yaml").is_file():
            _cli("simulate", ds, "--seed", SIM["seed"], "--frames", SIM["frames"], "--width", SIM["width"],
                 "--height", SIM["height"], "--force")
    elif not (ds / "dataset.yaml").is_file():
        src = real / name
        fmt = "rwhe" if (src / "RobotPosesVec.txt").exists() else "tabb"
        _cli("import", fmt, src, ds, *(["--board", BOARDS[name]] if name in BOARDS else []))
    if not (res / "calibration.json").is_file():
        _cli("solve", ds, "--out", res, "--no-report", *(["--jackknife", "never"] if name == "sim" else []))
    return ds, res


# --- measurements ------------------------------------------------------------------------------

def sim_measures(ds_dir: Path, res_dir: Path, state, voxel_m: float) -> dict:
    import open3d as o3d
    import yaml
    from scipy.spatial import cKDTree

    from calib3r_graph.dense.fuse import read_dense_ply
    from calib3r_graph.io.dataset import load_dataset, pose_from_dict
    from calib3r_graph.simulate import scene_from_simulation

    gt = yaml.safe_load((ds_dir / "ground_truth.yaml").read_text())
    scene = scene_from_simulation(gt["simulation"])
    pts = read_dense_ply(res_dir / "dense.ply")["points"]
    dist = scene.scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy() * 1e3
    centres = np.array([pose_from_dict(v["base_T_cam"]).translation() for v in gt["views"].values()])
    near = cKDTree(centres).query(pts)[0]
    band = (near >= 0.4) & (near <= 0.6)
    # the surface two or more views see: each view's rays on a coarse grid, kept where another view sees
    # the same point unoccluded (its own ray hits within 1 % of the depth)
    ds = load_dataset(ds_dir)
    cam = next(iter(ds.cameras.values()))
    step = 8
    poses = [pose_from_dict(v["base_T_cam"]) for v in gt["views"].values()]
    hits, depth_maps = [], []
    for T in poses:
        d, P, _, _ = scene.raycast(cam.K, T, cam.width, cam.height)
        depth_maps.append(d)
        hits.append(P[::step, ::step][np.isfinite(d[::step, ::step])])
    seen2 = []
    for i, P in enumerate(hits):
        count = np.ones(len(P), int)
        for j, T in enumerate(poses):
            if j == i:
                continue
            q = P @ T.inverse().rotation().matrix().T + T.inverse().translation()
            z = q[:, 2]
            uv = np.round(q[:, :2] / np.maximum(z[:, None], 1e-9) * np.diag(cam.K)[:2] + cam.K[:2, 2]).astype(int)
            ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
            vis = np.zeros(len(P), bool)
            vis[ok] = np.abs(depth_maps[j][uv[ok, 1], uv[ok, 0]] - z[ok]) < 0.01 * z[ok]
            count += vis
        seen2.append(P[count >= 2])
    surface = np.concatenate(seen2)
    covered = cKDTree(pts).query(surface, distance_upper_bound=2 * voxel_m)[0] < np.inf
    return {"distance_median_mm": float(np.median(dist)), "distance_p90_mm": float(np.percentile(dist, 90)),
            "distance_0.4-0.6m_median_mm": float(np.median(dist[band])) if band.any() else None,
            "distance_0.4-0.6m_p90_mm": float(np.percentile(dist[band], 90)) if band.any() else None,
            "points_0.4-0.6m": int(band.sum()),
            "coverage_of_surface_seen_by_2_views": float(covered.mean()),
            "coverage_radius_mm": 2 * voxel_m * 1e3}


def board_measures(ds_dir: Path, res_dir: Path) -> dict:
    import gtsam

    from calib3r_graph.dense.fuse import read_dense_ply
    from calib3r_graph.dense.views import read_result
    from calib3r_graph.evaluation import pattern
    from calib3r_graph.evaluation.compare import run_method
    from calib3r_graph.evaluation.evaluate import _adjacent_pairs, _normalised_rays
    from calib3r_graph.geometry import mean_pose
    from calib3r_graph.io import boards
    from calib3r_graph.io.dataset import load_dataset
    from calib3r_graph.io.predictions import view_id
    from calib3r_graph.solver.graph import NoiseOptions

    ds = load_dataset(ds_dir, skip_missing=True)
    cam_name = next(iter(ds.cameras))
    cam = ds.cameras[cam_name]
    dets = pattern.detect(ds, cam_name)
    X, cov = run_method("pattern-ba", ds, None, NoiseOptions())
    X = X[cam_name]
    base_T_board = mean_pose([ds.base_T_ee[d.frame].compose(X).compose(d.cam_T_board) for d in dets])
    obj = boards.points(boards.from_pattern(ds.pattern, ds.root / "dataset.yaml"))
    lo, hi = obj.min(0), obj.max(0)
    pts = read_dense_ply(res_dir / "dense.ply")["points"]
    Tb = base_T_board.inverse()
    local = pts @ Tb.rotation().matrix().T + Tb.translation()
    on = (local[:, 0] >= lo[0]) & (local[:, 0] <= hi[0]) & (local[:, 1] >= lo[1]) & (local[:, 1] <= hi[1]) & \
        (np.abs(local[:, 2]) < 0.01)  # 10 mm: far beyond any calibration error worth measuring here
    out = {"board_points": int(on.sum()), "pattern_ba_ee_T_cam_t_mm": (X.translation() * 1e3).tolist(),
           "board_detections": len(dets)}
    if on.sum() < 100:
        return {**out, "status": "the dense cloud has fewer than 100 points on the board"}
    P = local[on]
    c = P.mean(0)
    _, _, Vt = np.linalg.svd(P - c, full_matrices=False)
    n = Vt[2] * np.sign(Vt[2][2] or 1)
    resid = (P - c) @ n
    # the fitted plane against the reference board plane (z = 0 in board coordinates), along its normal
    out.update({"flatness_rms_mm": float(np.sqrt(np.mean(resid ** 2)) * 1e3),
                "plane_offset_to_pattern_ba_mm": float(c[2] * 1e3),
                "plane_tilt_to_pattern_ba_deg": float(np.degrees(np.arccos(min(1.0, abs(n[2])))))})
    # What the hand-eye's own uncertainty allows along the normal: a translation error dt of ee_T_cam moves
    # view i's surface by (ee_R_base_i n_base) . dt along the board normal, so the plane moves by m . dt with
    # m the mean of those directions in the ee frame, and its sigma is sqrt(m^T C m) for ours, pattern-ba's
    # and their sum (the goal's "combined sigma"). Beside it, the board plane through our own solved poses
    # (each view's PnP board pose composed with its solved base_T_cam): the difference of the dense plane
    # to that one is the dense depth's own offset, the rest is the two hand-eyes' difference.
    n_base = Tb.rotation().matrix().T @ n
    m = np.mean([ds.base_T_ee[d.frame].rotation().matrix().T @ n_base for d in dets], axis=0)
    cal = json.loads((res_dir / "calibration.json").read_text())["cameras"][cam_name]
    R_ours = np.asarray(cal["T_ee_cam"], float)[:3, :3]
    sig = {"ours": float(np.sqrt(m @ R_ours @ np.asarray(cal["covariance"], float)[3:, 3:] @ R_ours.T @ m) * 1e3)}
    if cov and cam_name in cov:
        R = X.rotation().matrix()
        sig["pattern_ba"] = float(np.sqrt(m @ R @ np.asarray(cov[cam_name])[3:, 3:] @ R.T @ m) * 1e3)
    sig["combined"] = float(np.hypot(sig["ours"], sig.get("pattern_ba", 0.0)))
    out["plane_sigma_along_normal_mm"] = sig
    result = read_result(res_dir)
    own = result.base_T_cam
    through = [Tb.compose(gtsam.Pose3(own[view_id(cam_name, d.frame)])).compose(d.cam_T_board).transformFrom(
        np.r_[(lo[:2] + hi[:2]) / 2, 0.0])[2] for d in dets if view_id(cam_name, d.frame) in own]
    out["board_plane_through_solved_poses_mm"] = float(np.mean(through) * 1e3)
    out["hand_eye_difference_along_normal_mm"] = float(
        m @ (np.asarray(cal["T_ee_cam"], float)[:3, 3] - X.translation()) * 1e3)
    # the square size on the dense cloud: corner rays through the solved poses, onto the dense plane
    c_base = base_T_board.transformFrom(c)
    pairs, spacing = _adjacent_pairs(obj)
    sizes = []
    for d in dets:
        v = view_id(cam_name, d.frame)
        if v not in result.base_T_cam:
            continue
        T = result.base_T_cam[v]
        rays = _normalised_rays(cam, d.uv) @ T[:3, :3].T
        o = T[:3, 3]
        s = ((c_base - o) @ n_base) / (rays @ n_base)
        Q = np.full((len(obj), 3), np.nan)
        ids = np.arange(len(obj)) if d.ids is None else np.asarray(d.ids)
        Q[ids] = o + rays * s[:, None]
        dd = np.linalg.norm(Q[pairs[:, 0]] - Q[pairs[:, 1]], axis=1)
        sizes.append(dd[np.isfinite(dd)])
    sizes = np.concatenate(sizes)
    out.update({"square_size_dense_mm": float(np.mean(sizes) * 1e3), "square_size_printed_mm": spacing * 1e3,
                "square_size_error_percent": float((np.mean(sizes) - spacing) / spacing * 100)})
    return out


def sweep(ds_dir: Path, state) -> dict:
    from calib3r_graph.dense import check
    from calib3r_graph.io.dataset import load_dataset

    ds = load_dataset(ds_dir, skip_missing=True)
    cam = next(iter(state.views.values())).camera
    X0 = np.linalg.inv(ds.base_T_ee[next(iter(state.views.values())).frame].matrix()) @ \
        next(iter(state.views.values())).chain_T_cam

    def run(X):
        poses = {v: ds.base_T_ee[dv.frame].matrix() @ X for v, dv in state.views.items()}
        return check.disagreement(state.depths, state.rays, state.views, state.check_pairs, poses)

    rows = [{"perturbation": "none", **run(X0)}]
    for kind, values, unit in (("translation_mm", SWEEP_MM, "mm"), ("rotation_deg", SWEEP_DEG, "deg")):
        for value in values:
            per_axis = [run(check.perturbed(X0, axis, **{kind: value})) for axis in range(3)]
            rows.append({"perturbation": f"{value:g} {unit}", "camera": cam,
                         "median_mm_per_axis": [r["median_mm"] for r in per_axis],
                         "p90_mm_per_axis": [r["p90_mm"] for r in per_axis]})
    return {"rows": rows}


def picture(res_dir: Path, path: Path, title: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from calib3r_graph.dense.fuse import read_dense_ply

    d = read_dense_ply(res_dir / "dense.ply")
    P, C = d["points"], d["colors"]
    if len(P) > 300000:
        keep = np.random.default_rng(0).choice(len(P), 300000, replace=False)
        P, C = P[keep], C[keep]
    lo, hi = np.percentile(P, [2, 98], axis=0)  # stray points would dwarf the scene (as the report does)
    keep = np.all((P >= lo - 0.1 * (hi - lo)) & (P <= hi + 0.1 * (hi - lo)), axis=1)
    P, C = P[keep], C[keep]
    c = np.median(P, 0)
    _, _, Vt = np.linalg.svd(P[::10] - c, full_matrices=False)  # the cloud's main plane
    q = (P - c) @ Vt.T * 1e3
    fig = plt.figure(figsize=(15, 6.5))
    ax = fig.add_subplot(1, 2, 1)
    order = np.argsort(q[:, 2])  # nearest to the viewer last
    ax.scatter(q[order, 0], q[order, 1], c=C[order], s=0.3, linewidths=0)
    ax.set_aspect("equal")
    ax.set_xlabel("mm")
    ax.set_ylabel("mm")
    ax.set_title("along the cloud's main normal")
    ax = fig.add_subplot(1, 2, 2, projection="3d")
    ax.scatter(q[:, 0], q[:, 1], q[:, 2], c=C, s=0.2, linewidths=0)
    ax.view_init(elev=20, azim=-60)
    ax.set_box_aspect(np.ptp(q, axis=0))
    ax.set_xlabel("mm")
    ax.set_ylabel("mm")
    ax.set_zlabel("mm")
    ax.set_title("oblique")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --- one run, in a child process ----------------------------------------------------------------

def one(name: str, work: Path, real: Path, out_json: Path):
    from calib3r_graph.dense.run import DenseOptions, reconstruct_with_state
    from calib3r_graph.dense.views import read_result
    from calib3r_graph.io.dataset import load_dataset

    ds_dir, res_dir = prepare(name, work, real)
    from calib3r_graph.errors import SolveError

    voxel = VOXEL_START_MM
    while True:
        opt = DenseOptions(source="stereo", progress=False, voxel_mm=voxel)
        t = time.perf_counter()
        try:
            figures, state = reconstruct_with_state(load_dataset(ds_dir, skip_missing=True), read_result(res_dir),
                                                    opt, res_dir)
            break
        except SolveError as e:  # no view kept at this voxel size
            if voxel * 2 > VOXEL_MAX_MM:
                raise
            print(f"{name}: {e}; voxel {voxel:g} -> {voxel * 2:g} mm", flush=True)
            voxel *= 2
    figures["wall_s"] = time.perf_counter() - t
    cam = next(iter(load_dataset(ds_dir, skip_missing=True).cameras.values()))
    row = {"name": name, "dense": figures, "image": f"{cam.width}x{cam.height}"}
    if name == "sim":
        row["sim"] = sim_measures(ds_dir, res_dir, state, opt.voxel_mm * 1e-3)
    else:
        row["board"] = board_measures(ds_dir, res_dir)
    row["sweep"] = sweep(ds_dir, state)
    out_json.write_text(json.dumps(row, indent=1))


def table(rows: list) -> str:
    f = lambda x, spec=".2f": "–" if x is None else format(x, spec)  # noqa: E731
    lines = ["| run | image | views (skipped) | points before voxel | points in dense.ply | coverage per view | "
             "s per view (wall) | CPU s per view | peak memory | disagreement median / p90 |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        d = r["dense"]
        g = d["disagreement"]
        lines.append(f"| {r['name']} ({d['voxel_mm']:g} mm voxel) | {r.get('image', '')} | "
                     f"{d['views_used']} ({len(d['views_skipped'])}) | "
                     f"{d['points_before_voxel']} | {d['points']} | {100 * d['coverage_mean']:.0f} % | "
                     f"{d['seconds_per_view']:.1f} | {f(d.get('cpu_seconds_per_view'), '.1f')} | "
                     f"{d['peak_memory_mb'] / 1024:.1f} GB | {f(g['median_mm'])} / {f(g['p90_mm'])} mm |")
    for r in rows:
        if "sim" in r:
            s = r["sim"]
            lines += ["", f"Simulator ({r['name']}): distance to the true surface median {f(s['distance_median_mm'])} "
                          f"mm, p90 {f(s['distance_p90_mm'])} mm; 0.4-0.6 m from the nearest camera: median "
                          f"{f(s['distance_0.4-0.6m_median_mm'])} mm, p90 {f(s['distance_0.4-0.6m_p90_mm'])} mm "
                          f"({s['points_0.4-0.6m']} points); {100 * s['coverage_of_surface_seen_by_2_views']:.0f} % "
                          f"of the surface that two or more views see is within {s['coverage_radius_mm']:g} mm of "
                          "a dense point."]
    lines += ["", "| recording | board points | flatness RMS | plane to pattern-ba (along normal) | of which hand-eyes "
                  "/ dense depth | sigma along normal: ours / pattern-ba / combined | tilt | square on dense / printed |",
              "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        b = r.get("board")
        if not b:
            continue
        if "status" in b:
            lines.append(f"| {r['name']} | {b['board_points']} | {b['status']} | | | | | |")
            continue
        sg = b.get("plane_sigma_along_normal_mm", {})
        own = (None if "board_plane_through_solved_poses_mm" not in b
               else b["plane_offset_to_pattern_ba_mm"] - b["board_plane_through_solved_poses_mm"])
        lines.append(f"| {r['name']} | {b['board_points']} | {f(b['flatness_rms_mm'])} mm | "
                     f"{f(b['plane_offset_to_pattern_ba_mm'])} mm | {f(b.get('hand_eye_difference_along_normal_mm'))} / "
                     f"{f(own)} mm | {f(sg.get('ours'))} / {f(sg.get('pattern_ba'))} / {f(sg.get('combined'))} mm | "
                     f"{f(b['plane_tilt_to_pattern_ba_deg'], '.3f')}° | "
                     f"{f(b['square_size_dense_mm'], '.3f')} / {b['square_size_printed_mm']:.3f} mm "
                     f"({b['square_size_error_percent']:+.2f} %) |")
    lines += ["", "Cross-view surface disagreement (median mm, worst of the three ee axes; p90 in dense.json) with "
                  "ee_T_cam moved or turned:", "",
              "| run | solved | " + " | ".join(f"{v:g} mm" for v in SWEEP_MM) + " | "
              + " | ".join(f"{v:g}°" for v in SWEEP_DEG) + " |", "|---|" + "---|" * 7]
    for r in rows:
        sw = r["sweep"]["rows"]
        lines.append(f"| {r['name']} | {f(sw[0]['median_mm'])} | "
                     + " | ".join(f(max(x for x in s["median_mm_per_axis"] if x is not None)) for s in sw[1:]) + " |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="/tmp/calib3r-dense")
    ap.add_argument("--real", default=str(ROOT.parent / "shared" / "real"))
    ap.add_argument("--recordings", default="rwhe_kuka_1,rwhe_kuka_2,tabb_ds1")
    ap.add_argument("--skip-sim", action="store_true")
    ap.add_argument("--table-only", action="store_true", help="rebuild dense.md from the runs' JSON in --work")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    ap.add_argument("--out-json", help=argparse.SUPPRESS)
    a = ap.parse_args()
    work, real = Path(a.work), Path(a.real)
    work.mkdir(parents=True, exist_ok=True)
    if a.one:
        one(a.one, work, real, Path(a.out_json))
        return
    names = ([] if a.skip_sim else ["sim"]) + [n for n in a.recordings.split(",") if n and (real / n).is_dir()]
    rows = []
    for name in names:
        out = work / f"{name}_bench.json"
        if a.table_only:
            rows.append(json.loads(out.read_text()))
            continue
        subprocess.run([sys.executable, __file__, "--work", str(work), "--real", str(real), "--one", name,
                        "--out-json", str(out)], check=True)
        rows.append(json.loads(out.read_text()))
        print(f"{name}: done", file=sys.stderr)
    results = ROOT / "bench" / "results"
    (results / "dense.json").write_text(json.dumps(rows, indent=1))
    text = table(rows)
    (results / "dense.md").write_text(text)
    real_rows = [r for r in rows if r["name"] != "sim"]
    if real_rows:
        name = real_rows[0]["name"]
        picture(work / f"{name}_res", results / f"dense_{name}.png", f"{name}: dense.ply (RGB, SGBM on the solved "
                                                                       "poses), robot base frame")
    print(text)


if __name__ == "__main__":
    main()
