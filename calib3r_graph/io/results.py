"""Writing what ``solve`` found: calibration.json (calib3r-calibration/1), trajectory.csv,
reconstruction.ply and summary.txt, all staged and moved into place only on success."""

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib3r_graph.io.dataset import Dataset, pose_to_row
from calib3r_graph.io.output import atomic_path, atomic_write_json, atomic_write_text, staged_directory
from calib3r_graph.io.predictions import Predictions, split_view_id
from factors.match3d import depth_correction_basis

AXES = ["rx", "ry", "rz", "x", "y", "z"]


def covariance_in_ee_frame(T_ee_cam, cov):
    """Rotate the tangent covariance (body frame [w, v]) into the ee frame, for per-axis sigmas."""
    R = T_ee_cam.rotation().matrix()
    G = np.zeros((6, 6))
    G[:3, :3] = G[3:, 3:] = R
    return G @ cov @ G.T


def sigma_ee_frame(sig: np.ndarray) -> dict:
    """Per-axis sigmas of the ee-frame covariance's diagonal (rad, m) in degrees and mm."""
    return {"rx_deg": float(np.degrees(sig[0])), "ry_deg": float(np.degrees(sig[1])),
            "rz_deg": float(np.degrees(sig[2])), "x_mm": float(sig[3] * 1e3),
            "y_mm": float(sig[4] * 1e3), "z_mm": float(sig[5] * 1e3)}


def largest_sigma(sigmas: dict) -> tuple[float, float]:
    """{camera: sigma_ee_frame} -> the largest (mm, deg) over cameras and ee axes."""
    return (max(s[a] for s in sigmas.values() for a in ("x_mm", "y_mm", "z_mm")),
            max(s[a] for s in sigmas.values() for a in ("rx_deg", "ry_deg", "rz_deg")))


def tangent_in_ee_frame(R_ee_cam, xi) -> dict:
    """A tangent step [w, v] of ee_T_cam (body frame; rad, m) rotated into the ee frame, signed, in
    degrees and mm (the keys of sigma_ee_frame)."""
    R = np.asarray(R_ee_cam)
    return sigma_ee_frame(np.r_[R @ np.asarray(xi)[:3], R @ np.asarray(xi)[3:]])


def uncertainty_report(T_ee_cam, cov) -> dict:
    C = covariance_in_ee_frame(T_ee_cam, cov)
    sig = np.sqrt(np.maximum(np.diag(C), 0))
    s = np.outer(sig, sig)
    corr = np.divide(C, s, out=np.zeros_like(C), where=s > 0)  # a zero share (e.g. no systematic part): no correlation
    pairs = sorted(((abs(corr[i, j]), AXES[i], AXES[j], corr[i, j]) for i in range(6) for j in range(i + 1, 6)),
                   reverse=True)[:3]
    return {"sigma_ee_frame": sigma_ee_frame(sig),
            "strongest_correlations": [{"axes": [a, b], "rho": float(r)} for _, a, b, r in pairs]}


def calibration_json(sol, predictions_name: str) -> dict:
    cams = {}
    for c, X in sol.ee_T_cam.items():
        lam, lam_sigma = sol.metric_scale[c]
        cams[c] = {"T_ee_cam": X.matrix().tolist(), "covariance": np.asarray(sol.covariance[c]).tolist(),
                   "metric_scale": lam, "metric_scale_sigma": lam_sigma,
                   **uncertainty_report(X, sol.covariance[c])}
        if c in sol.covariance_model:  # the noise model's marginal alone, beside the total
            cams[c]["covariance_model"] = np.asarray(sol.covariance_model[c]).tolist()
            cams[c]["sigma_ee_frame_model"] = uncertainty_report(X, sol.covariance_model[c])["sigma_ee_frame"]
        if c in sol.systematic:  # the robot error field's share
            cams[c]["covariance_systematic"] = np.asarray(sol.systematic[c].covariance).tolist()
            cams[c]["sigma_ee_frame_systematic"] = uncertainty_report(X, sol.systematic[c].covariance)["sigma_ee_frame"]
        cm = getattr(sol, "camera_model", {}).get(c)
        if cm is not None:  # the intrinsics' share (solver/camera_model.py); absent when not propagated
            cams[c]["camera_model"] = cm.to_json()
            if cm.propagated:
                cams[c]["covariance_camera_model"] = np.asarray(cm.covariance).tolist()
                cams[c]["sigma_ee_frame_camera_model"] = uncertainty_report(X, cm.covariance)["sigma_ee_frame"]
    return {"format": "calib3r-calibration/1", "cameras": cams,
            "covariance_convention": "tangent of ee_T_cam, right perturbation T = T_hat Exp([w; v]), "
                                     "order [wx, wy, wz, vx, vy, vz] (rad, m); sigma_ee_frame rotated into the ee frame; "
                                     "covariance = covariance_model (noise model) + covariance_systematic "
                                     "(solver.systematic: kinematic error field measured from the robot residuals), "
                                     "covered with the jackknife's spread when it ran, + covariance_camera_model "
                                     "(solver.camera_model: the intrinsics' stated sigma, when given)",
            "metric_scale_meaning": "metres per unit of the frontend's depth (geometric mean over the camera's views)",
            "predictions": predictions_name, "views_dropped": sol.views_dropped,
            "observability": sol.diagnostics, "solver": sol.stats}


def trajectory_csv(sol) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["camera", "frame", "x", "y", "z", "qx", "qy", "qz", "qw"])
    for v in sorted(sol.base_T_cam):
        cam, frame = split_view_id(v)
        w.writerow([cam] + pose_to_row(frame, sol.base_T_cam[v]))
    return buf.getvalue()


@dataclass
class PointCloud:
    """A coloured point cloud: ``points`` (N, 3) in metres, ``colors`` (N, 3) RGB in [0, 1]."""

    points: np.ndarray
    colors: np.ndarray

    def __len__(self):
        return len(self.points)


def metric_depth(vp, depth_scale: float, correction, uv) -> np.ndarray:
    """A view's corrected metric depth at grid pixels ``uv`` (N, 2): ``s (1 + phi(u) c) d(u)``, as the
    solver models it (factors/match3d.py)."""
    h, w = vp.depth.shape
    iu = np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1)
    iv = np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1)
    return vp.depth[iv, iu] * depth_scale * (1 + depth_correction_basis(np.asarray(uv, float), w, h)
                                             @ np.asarray(correction))


def voxel_down_sample(points: np.ndarray, colors: np.ndarray, voxel: float):
    """One point per occupied voxel: the mean of its points and of their colours (as Open3D does)."""
    if len(points) == 0:
        return points, colors
    cell = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    dims = cell.max(axis=0) + 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    mean = lambda x: np.stack([np.bincount(inverse, weights=x[:, k], minlength=len(counts)) for k in range(3)],
                              1) / counts[:, None]
    return mean(points), mean(colors)


def write_ply(path, points: np.ndarray, colors: np.ndarray):
    """Binary little-endian PLY: float32 x, y, z and uchar red, green, blue per vertex."""
    vertex = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                          ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for k, name in enumerate("xyz"):
        vertex[name] = points[:, k]
    rgb = np.clip(np.round(np.asarray(colors) * 255), 0, 255).astype(np.uint8)
    for k, name in enumerate(("red", "green", "blue")):
        vertex[name] = rgb[:, k]
    header = ("ply\nformat binary_little_endian 1.0\ncomment calib3r-graph reconstruction, robot base frame, "
              f"metres\nelement vertex {len(vertex)}\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vertex.tobytes())


def point_cloud(ds: Dataset, preds: Predictions, sol, max_points_per_view=60000, voxel_m=0.002) -> PointCloud:
    """Dense metric cloud in the robot base frame, coloured from the images where present."""
    import cv2

    pts_all, col_all = [], []
    for v, T in sol.base_T_cam.items():
        vp = preds.views[v]
        h, w = vp.depth.shape
        conf_ok = vp.conf > 0.5 * np.median(vp.conf[vp.conf > 0])
        idx = np.flatnonzero((vp.depth > 0).ravel() & conf_ok.ravel())
        if len(idx) > max_points_per_view:
            idx = idx[:: len(idx) // max_points_per_view + 1]
        uv = np.stack([idx % w, idx // w], 1).astype(np.float64)
        d = metric_depth(vp, sol.depth_scale[v], sol.depth_correction[v], uv)
        rays = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(vp.K).T
        P = (rays * d[:, None]) @ T.rotation().matrix().T + T.translation()
        cam, frame = split_view_id(v)
        img_path = ds.image_path(cam, frame)
        colours = np.full((len(P), 3), 0.6)
        if img_path is not None:
            img = cv2.imread(str(img_path), cv2.IMREAD_COLOR)
            if img is not None:
                camera = ds.cameras[cam]
                if np.any(camera.dist):
                    px, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.K, camera.dist)
                else:  # a pinhole: rays are [x, y, 1]
                    px = rays[:, :2] * np.diag(camera.K)[:2] + camera.K[:2, 2]
                px = np.round(px.reshape(-1, 2)).astype(int)
                ok = (px[:, 0] >= 0) & (px[:, 0] < img.shape[1]) & (px[:, 1] >= 0) & (px[:, 1] < img.shape[0])
                colours[ok] = img[px[ok, 1], px[ok, 0], ::-1] / 255.0
        pts_all.append(P)
        col_all.append(colours)
    points, colors = voxel_down_sample(np.concatenate(pts_all), np.concatenate(col_all), voxel_m)
    return PointCloud(points, colors)


def summary_text(sol, ds: Dataset, predictions_name: str) -> str:
    lines = [f"calib3r-graph: {ds.root} — predictions '{predictions_name}', {sol.stats['views_used']} views, "
             f"{sol.stats['pairs_used']} pairs, {sol.stats['matches_used']} matches"]
    for c, X in sol.ee_T_cam.items():
        rep = uncertainty_report(X, sol.covariance[c])["sigma_ee_frame"]
        t = X.translation() * 1e3
        rpy = np.degrees(X.rotation().rpy())
        lam, lam_sigma = sol.metric_scale[c]
        lines += [f"  {c}: ee_T_cam t = [{t[0]:8.2f} {t[1]:8.2f} {t[2]:8.2f}] mm   rpy = [{rpy[0]:8.3f} {rpy[1]:8.3f} "
                  f"{rpy[2]:8.3f}] deg",
                  f"        sigma t = [{rep['x_mm']:.2f} {rep['y_mm']:.2f} {rep['z_mm']:.2f}] mm   "
                  f"sigma r = [{rep['rx_deg']:.3f} {rep['ry_deg']:.3f} {rep['rz_deg']:.3f}] deg   "
                  f"metric scale {lam:.5g} ± {lam_sigma:.2g} m/unit"]
        if c in sol.covariance_model:
            mod = uncertainty_report(X, sol.covariance_model[c])["sigma_ee_frame"]
            sysm = sol.systematic[c]
            field = (f"robot error field {sysm.gradient_mm_per_m:.2f} mm/m, {sysm.gradient_deg_per_m:.3f} deg/m"
                     if sysm.measured else f"robot error field not measurable from {sysm.poses} poses")
            jk = sol.stats.get("jackknife", {}).get(c)
            lines.append(f"        of which noise model t = [{mod['x_mm']:.2f} {mod['y_mm']:.2f} {mod['z_mm']:.2f}] mm, "
                         f"r = [{mod['rx_deg']:.3f} {mod['ry_deg']:.3f} {mod['rz_deg']:.3f}] deg; "
                         + _camera_model_share(X, getattr(sol, "camera_model", {}).get(c))
                         + f"; the rest: {field}"
                         + (f"; the total covers the jackknife of {jk['solves']} leave-one-pose-out solves" if jk else ""))
    for c, X in sol.ee_T_cam.items():
        corr = uncertainty_report(X, sol.covariance[c])["strongest_correlations"][0]
        lines.append(f"  {c}: strongest correlation {corr['axes'][0]}-{corr['axes'][1]} {corr['rho']:+.2f}")
    lines += [f"  ! {m}" for m in sol.diagnostics]
    lines += [f"  ! left out {d['view']}: {d['reason']}" for d in sol.views_dropped]  # [{"view", "reason"}]
    for c, jk in sol.stats.get("jackknife", {}).items():
        r = jk["ratio_to_reported"]
        lines.append(f"  {c}: jackknife ({jk['solves']} solves) / modelled sigma: rotation "
                     f"{r[0]:.1f} {r[1]:.1f} {r[2]:.1f}, translation {r[3]:.1f} {r[4]:.1f} {r[5]:.1f}")
    tm = sol.stats["timings_s"]
    lines.append(f"  time: init {tm['initialisation']:.1f} s, optimisation {tm['optimisation']:.1f} s, "
                 f"covariance {tm['covariance']:.1f} s"
                 + (f", jackknife {tm['jackknife']:.1f} s" if "jackknife" in tm else "")
                 + (f", camera model {tm['camera_model']:.1f} s" if tm.get("camera_model", 0) >= 0.05 else "")
                 + "; LM iterations "
                 f"{'+'.join(str(r['iterations']) for r in sol.stats['rounds'])}")
    return "\n".join(lines) + "\n"


def _camera_model_share(X, cm) -> str:
    """The summary's words for the camera model's share (solver/camera_model.py)."""
    if cm is None or not cm.propagated:
        return ("camera model not in the sigma (no intrinsics sigma: params_sigma in dataset.yaml or "
                "--intrinsics-sigma-px)")
    s = uncertainty_report(X, cm.covariance)["sigma_ee_frame"]
    given = " ".join(f"{x:.2g}" for x in cm.params_sigma)
    return (f"camera model t = [{s['x_mm']:.2f} {s['y_mm']:.2f} {s['z_mm']:.2f}] mm, r = [{s['rx_deg']:.3f} "
            f"{s['ry_deg']:.3f} {s['rz_deg']:.3f}] deg (fx fy cx cy ± {given} px, {cm.source})")


def write_results(out_dir, ds: Dataset, preds: Predictions, sol, write_cloud=True, extra=None, dense=None) -> str:
    """``extra(stage, calibration, summary, cloud)``: writes more files into the same staging folder,
    e.g. report.html (calib3r_graph.report.solve_report_writer); ``cloud`` is None without write_cloud.
    ``dense(stage) -> (figures, summary lines)``: solve --dense (calib3r_graph.dense), run once the
    trajectory, views.npz and cloud are staged; its figures go into calibration.json ("dense") and summary.txt."""
    out_dir = Path(out_dir)
    summary = summary_text(sol, ds, preds.name)
    with staged_directory(out_dir) as stage:
        calibration = calibration_json(sol, preds.name)
        atomic_write_text(stage / "trajectory.csv", trajectory_csv(sol))
        write_views(stage / "views.npz", sol)
        pcd = None
        if write_cloud:
            pcd = point_cloud(ds, preds, sol)
            with atomic_path(stage / "reconstruction.ply") as tmp:
                write_ply(tmp, pcd.points, pcd.colors)
        if dense is not None:
            calibration["dense"], lines = dense(stage)
            summary += lines
        atomic_write_json(stage / "calibration.json", calibration)
        atomic_write_text(stage / "summary.txt", summary)
        if extra is not None:
            extra(stage, calibration, summary, pcd)
    return summary


def write_views(path, sol):
    """``views.npz``: each view's solved state, for ``evaluate`` to rebuild the reconstruction: ``view``
    ids, ``base_T_cam`` (N, 4, 4), ``depth_scale`` (N,) metres per frontend unit and ``depth_correction``
    (N, K) coefficients of ``1 + phi(u) c`` (factors/match3d.py)."""
    from calib3r_graph.io.output import atomic_savez

    views = sorted(sol.base_T_cam)
    atomic_savez(path, view=np.array(views), base_T_cam=np.array([sol.base_T_cam[v].matrix() for v in views]),
                 depth_scale=np.array([sol.depth_scale[v] for v in views], dtype=float),
                 depth_correction=np.array([np.asarray(sol.depth_correction[v], float) for v in views]))


@dataclass
class ViewStates:
    """The per-view part of a Solution (what ``views.npz`` holds)."""

    base_T_cam: dict  # view -> gtsam.Pose3
    depth_scale: dict  # view -> float
    depth_correction: dict  # view -> (K,)


def read_views(path) -> ViewStates:
    import gtsam

    from calib3r_graph.errors import InputError

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "missing (written by 'calib3r-graph solve'; solve again to get it)")
    try:
        with np.load(path) as z:
            views = [str(v) for v in z["view"]]
            T, s, c = z["base_T_cam"], z["depth_scale"], z["depth_correction"]
            return ViewStates({v: gtsam.Pose3(np.asarray(T[i], float)) for i, v in enumerate(views)},
                              {v: float(s[i]) for i, v in enumerate(views)},
                              {v: np.asarray(c[i], float) for i, v in enumerate(views)})
    except Exception as e:  # noqa: BLE001 - any corruption of the file is the file's fault
        first = next(iter(str(e).strip().splitlines()), "")
        raise InputError(path, f"not a views.npz written by solve ({type(e).__name__}: {first})") from None


def read_calibration(path) -> dict:
    return json.loads(Path(path).read_text())
