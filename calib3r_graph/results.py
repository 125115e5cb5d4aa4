"""Writing what ``solve`` found: calibration.json (calib3r-calibration/1), trajectory.csv,
reconstruction.ply and summary.txt, all staged and moved into place only on success."""

import csv
import io
import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from calib3r_graph.dataset import Dataset, pose_to_row
from calib3r_graph.output import atomic_path, atomic_write_json, atomic_write_text, staged_directory
from calib3r_graph.predictions import Predictions, split_view_id
from factors.match3d import depth_correction_basis

AXES = ["rx", "ry", "rz", "x", "y", "z"]


def covariance_in_ee_frame(T_ee_cam, cov):
    """Rotate the tangent covariance (body frame [w, v]) into the ee frame, for per-axis sigmas."""
    R = T_ee_cam.rotation().matrix()
    G = np.zeros((6, 6))
    G[:3, :3] = G[3:, 3:] = R
    return G @ cov @ G.T


def uncertainty_report(T_ee_cam, cov) -> dict:
    C = covariance_in_ee_frame(T_ee_cam, cov)
    sig = np.sqrt(np.maximum(np.diag(C), 0))
    corr = C / np.outer(sig, sig)
    pairs = sorted(((abs(corr[i, j]), AXES[i], AXES[j], corr[i, j]) for i in range(6) for j in range(i + 1, 6)),
                   reverse=True)[:3]
    return {"sigma_ee_frame": {"rx_deg": float(np.degrees(sig[0])), "ry_deg": float(np.degrees(sig[1])),
                               "rz_deg": float(np.degrees(sig[2])), "x_mm": float(sig[3] * 1e3),
                               "y_mm": float(sig[4] * 1e3), "z_mm": float(sig[5] * 1e3)},
            "strongest_correlations": [{"axes": [a, b], "rho": float(r)} for _, a, b, r in pairs]}


def calibration_json(sol, predictions_name: str) -> dict:
    cams = {}
    for c, X in sol.ee_T_cam.items():
        lam, lam_sigma = sol.metric_scale[c]
        cams[c] = {"T_ee_cam": X.matrix().tolist(), "covariance": np.asarray(sol.covariance[c]).tolist(),
                   "metric_scale": lam, "metric_scale_sigma": lam_sigma,
                   **uncertainty_report(X, sol.covariance[c])}
    return {"format": "calib3r-calibration/1", "cameras": cams,
            "covariance_convention": "tangent of ee_T_cam, right perturbation T = T_hat Exp([w; v]), "
                                     "order [wx, wy, wz, vx, vy, vz] (rad, m); sigma_ee_frame rotated into the ee frame",
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


def point_cloud(ds: Dataset, preds: Predictions, sol, max_points_per_view=60000, voxel_m=0.002):
    """Dense metric cloud in the robot base frame, coloured from the images where present."""
    pts_all, col_all = [], []
    for v, T in sol.base_T_cam.items():
        vp = preds.views[v]
        h, w = vp.depth.shape
        conf_ok = vp.conf > 0.5 * np.median(vp.conf[vp.conf > 0])
        idx = np.flatnonzero((vp.depth > 0).ravel() & conf_ok.ravel())
        if len(idx) > max_points_per_view:
            idx = idx[:: len(idx) // max_points_per_view + 1]
        uv = np.stack([idx % w, idx // w], 1).astype(np.float64)
        d = vp.depth.ravel()[idx] * sol.depth_scale[v] * (1 + depth_correction_basis(uv, w, h) @ sol.depth_correction[v])
        rays = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(vp.K).T
        P = (rays * d[:, None]) @ T.rotation().matrix().T + T.translation()
        cam, frame = split_view_id(v)
        img_path = ds.image_path(cam, frame)
        colours = np.full((len(P), 3), 0.6)
        if img_path is not None:
            img = cv2.imread(str(img_path), cv2.IMREAD_COLOR)
            if img is not None:
                camera = ds.cameras[cam]
                px, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.K, camera.dist)
                px = np.round(px.reshape(-1, 2)).astype(int)
                ok = (px[:, 0] >= 0) & (px[:, 0] < img.shape[1]) & (px[:, 1] >= 0) & (px[:, 1] < img.shape[0])
                colours[ok] = img[px[ok, 1], px[ok, 0], ::-1] / 255.0
        pts_all.append(P)
        col_all.append(colours)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(pts_all)))
    pcd.colors = o3d.utility.Vector3dVector(np.concatenate(col_all))
    return pcd.voxel_down_sample(voxel_m)


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
    for c, X in sol.ee_T_cam.items():
        corr = uncertainty_report(X, sol.covariance[c])["strongest_correlations"][0]
        lines.append(f"  {c}: strongest correlation {corr['axes'][0]}-{corr['axes'][1]} {corr['rho']:+.2f}")
    lines += [f"  ! {m}" for m in sol.diagnostics]
    for c, jk in sol.stats.get("jackknife", {}).items():
        r = jk["ratio_to_reported"]
        lines.append(f"  {c}: jackknife ({jk['solves']} solves) / reported sigma: rotation "
                     f"{r[0]:.1f} {r[1]:.1f} {r[2]:.1f}, translation {r[3]:.1f} {r[4]:.1f} {r[5]:.1f}")
    tm = sol.stats["timings_s"]
    lines.append(f"  time: init {tm['initialisation']:.1f} s, optimisation {tm['optimisation']:.1f} s, "
                 f"covariance {tm['covariance']:.1f} s; LM iterations "
                 f"{'+'.join(str(r['iterations']) for r in sol.stats['rounds'])}")
    return "\n".join(lines) + "\n"


def write_results(out_dir, ds: Dataset, preds: Predictions, sol, write_cloud=True) -> str:
    out_dir = Path(out_dir)
    summary = summary_text(sol, ds, preds.name)
    with staged_directory(out_dir) as stage:
        atomic_write_json(stage / "calibration.json", calibration_json(sol, preds.name))
        atomic_write_text(stage / "trajectory.csv", trajectory_csv(sol))
        atomic_write_text(stage / "summary.txt", summary)
        if write_cloud:
            pcd = point_cloud(ds, preds, sol)
            with atomic_path(stage / "reconstruction.ply") as tmp:
                if not o3d.io.write_point_cloud(str(tmp), pcd, write_ascii=False):
                    raise OSError(f"cannot write {tmp}")
    return summary


def read_calibration(path) -> dict:
    return json.loads(Path(path).read_text())
