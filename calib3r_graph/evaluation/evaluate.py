"""Evaluation with the paper's metrics.

e_t: Euclidean distance between the estimated and true ee_T_cam translations (m);
e_theta: angle of the rotation between them (rad) (both against ground_truth.yaml).
m_s − s, σ_s, δ_s: the metric reconstruction accuracy on the board (Calib3R's Table II), and, with the
simulator's geometry, the reconstruction's point-to-surface distances.
"""

import json
from pathlib import Path

import gtsam
import numpy as np

from calib3r_graph.errors import InputError
from calib3r_graph.geometry import pose_error
from calib3r_graph.io.dataset import ee_T_cam_by_camera, load_ground_truth


def hand_eye_errors(T_ee_cam: dict, ground_truth: dict) -> dict:
    """{camera: {"e_t_m", "e_theta_rad"}} for the cameras present in both."""
    out = {}
    for cam, X in T_ee_cam.items():
        if cam in ground_truth["hand_eye"]:
            X = X if isinstance(X, gtsam.Pose3) else gtsam.Pose3(np.asarray(X))
            et, er = pose_error(X, ground_truth["hand_eye"][cam])
            out[cam] = {"e_t_m": et, "e_theta_rad": float(np.radians(er))}
    return out


def load_calibration(result_dir) -> dict:
    path = Path(result_dir) / "calibration.json"
    if not path.is_file():
        raise InputError(path, "missing (run 'calib3r-graph solve' first)")
    try:
        calib = json.loads(path.read_text())
        return ee_T_cam_by_camera(calib["cameras"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise InputError(path, f"not a calib3r-calibration/1 file ({e})") from None


def evaluate(result_dir, dataset_dir) -> dict:
    """What ``evaluate`` writes to evaluation.json:

    * ``hand_eye``: e_t and e_theta per camera against ground_truth.yaml;
    * ``metric_scale``: the paper's m_s − s, σ_s and δ_s on the board, where dataset.yaml has a pattern
      (``metric_scale_accuracy``);
    * ``reconstruction``: median and 90 % point-to-surface distance, where the true geometry is known.
    """
    from calib3r_graph.io.dataset import load_dataset

    gt = load_ground_truth(dataset_dir)
    ds = load_dataset(dataset_dir, skip_missing=True)
    if gt is None and not ds.pattern:
        raise InputError(Path(dataset_dir) / "ground_truth.yaml",
                         "missing, and dataset.yaml has no pattern: nothing to evaluate against")
    report = {}
    if gt is not None:
        report["hand_eye"] = hand_eye_errors(load_calibration(result_dir), gt)
    else:
        load_calibration(result_dir)  # a result folder at all
    need_views = ds.pattern or (gt or {}).get("simulation")
    if need_views:
        from calib3r_graph.io.predictions import load_predictions
        from calib3r_graph.io.results import read_views

        try:
            states = read_views(Path(result_dir) / "views.npz")
        except InputError as e:
            if gt is None:
                raise
            report["not_evaluated"] = f"metric scale and reconstruction: {e}"  # a result from an older solve
            return report
        name = json.loads((Path(result_dir) / "calibration.json").read_text()).get("predictions")
        preds = load_predictions(ds.root, name, ds.cameras, set(ds.frames), skip_missing=True)
        if ds.pattern:
            report["metric_scale"] = metric_scale_accuracy(ds, preds, states)
        recon = reconstruction_accuracy(ds, preds, states, gt)
        if recon is not None:
            report["reconstruction"] = recon
    return report


# --- the paper's metric reconstruction accuracy (Calib3R, Table II) --------------------------------

DENSE_FRACTION = 0.9  # a view's depth is "dense" on the board when this share of its corners has depth


def _adjacent_pairs(obj: np.ndarray) -> tuple[np.ndarray, float]:
    """Pairs (i, j) of board points that are grid neighbours (at the smallest spacing), and that spacing."""
    d = np.linalg.norm(obj[:, None] - obj[None], axis=2)
    spacing = float(d[d > 0].min())
    i, j = np.nonzero(np.triu(np.abs(d - spacing) < 1e-6 * spacing, 1))
    return np.c_[i, j], spacing


def _normalised_rays(cam, uv) -> np.ndarray:
    """Image pixels (as detected, distorted) -> normalised camera rays [x, y, 1]."""
    import cv2

    xy = cv2.undistortPoints(np.asarray(uv, np.float64).reshape(-1, 1, 2), cam.K, cam.dist).reshape(-1, 2)
    return np.c_[xy, np.ones(len(xy))]


def _corrected_depth(vp, scale: float, correction, uv_grid) -> np.ndarray:
    """The solver's corrected metric depth ``s (1 + phi(u) c) d(u)`` at sub-pixel grid positions, bilinear;
    NaN where any of the four neighbours has no depth or zero confidence."""
    from factors.match3d import depth_correction_basis

    h, w = vp.depth.shape
    x, y = uv_grid[:, 0], uv_grid[:, 1]
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = x - x0, y - y0
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    d = np.zeros(len(x))
    valid = inside.copy()
    for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        dd, cc = vp.depth[y0 + dy, x0 + dx], vp.conf[y0 + dy, x0 + dx]
        valid &= (dd > 0) & (cc > 0)
        d += wgt * dd
    d = d * scale * (1 + depth_correction_basis(uv_grid, w, h) @ np.asarray(correction, float))
    return np.where(valid, d, np.nan)


def _triangulate(rays_by_view: list) -> np.ndarray:
    """Midpoint least squares over views: [(origin (3,), directions (N, 3) in the base frame, valid (N,))]
    -> (N, 3) points, NaN where fewer than two views see a point."""
    n = len(rays_by_view[0][1])
    A = np.zeros((n, 3, 3))
    b = np.zeros((n, 3))
    count = np.zeros(n, int)
    for o, dirs, ok in rays_by_view:
        norm = np.linalg.norm(dirs, axis=1)
        ok = ok & (norm > 0)  # a point this view does not see has no ray (its direction is zero)
        u = dirs[ok] / norm[ok, None]
        P = np.eye(3) - u[:, :, None] * u[:, None, :]  # projector orthogonal to each ray
        A[ok] += P
        b[ok] += P @ o
        count += ok
    out = np.full((n, 3), np.nan)
    good = count >= 2
    sv = np.linalg.svd(A[good], compute_uv=False)  # near-parallel rays: no intersection (condition >= 1e6)
    good[good] &= sv[:, -1] > 1e-6 * sv[:, 0]
    out[good] = np.linalg.solve(A[good], b[good][:, :, None])[:, :, 0]
    return out


def metric_scale_accuracy(ds, preds, states, detections: dict | None = None, use_depth: bool | None = None) -> dict:
    """The paper's m_s − s, σ_s and δ_s of the reconstruction, measured on the board.

    The board's points are detected in the images (``pattern.detect``), and taken in 3D from the
    reconstruction: the corrected metric depth of each view (its depth scale and smooth correction from
    the solve, ``states``: a Solution or ``read_views``) where the view's depth is dense on the board;
    otherwise triangulated from all such views' solved poses. m_s is the mean distance between adjacent
    board points in 3D, s the board's nominal spacing (the square size), σ_s their standard deviation,
    δ_s = |m_s − s| / s · 100. ``detections``: {camera: [Detection]} when already detected.
    ``use_depth``: None decides per view, True / False forces depth / triangulation."""
    from calib3r_graph.evaluation.pattern import detect
    from calib3r_graph.io import boards
    from calib3r_graph.io.predictions import view_id

    obj = boards.points(boards.from_pattern(ds.pattern, ds.root / "dataset.yaml"))
    pairs, spacing = _adjacent_pairs(obj)
    if detections is None:
        detections = {c: detect(ds, c) for c in ds.cameras}
    sizes, used_depth, tri, ref_R = [], 0, [], None
    for cam_name, dets in detections.items():
        cam = ds.cameras[cam_name]
        for det in dets:
            v = view_id(cam_name, det.frame)
            if v not in states.base_T_cam or v not in preds.views:
                continue
            ids = np.arange(len(obj)) if det.ids is None else np.asarray(det.ids)
            rays = _normalised_rays(cam, det.uv)
            vp = preds.views[v]
            uv_grid = (rays @ vp.K.T)[:, :2]
            depth = _corrected_depth(vp, states.depth_scale[v], states.depth_correction[v], uv_grid)
            dense = np.mean(np.isfinite(depth)) >= DENSE_FRACTION
            if use_depth or (use_depth is None and dense):
                P = np.full((len(obj), 3), np.nan)
                P[ids] = rays * depth[:, None]
                s = np.linalg.norm(P[pairs[:, 0]] - P[pairs[:, 1]], axis=1)
                sizes.append(s[np.isfinite(s)])
                used_depth += 1
                continue
            T = states.base_T_cam[v]
            R = T.rotation().matrix()
            if det.ids is None:  # a symmetric grid is found either way round: orient it like the first
                base_R_board = R @ det.cam_T_board.rotation().matrix()
                if ref_R is None:
                    ref_R = base_R_board
                elif np.trace(ref_R.T @ base_R_board) < 1:  # rotated by more than 90 degrees
                    ids = ids[::-1]
            dirs = np.zeros((len(obj), 3))
            ok = np.zeros(len(obj), bool)
            dirs[ids], ok[ids] = rays @ R.T, True
            tri.append((T.translation(), dirs, ok))
    used_tri = 0
    if len(tri) >= 2:
        P = _triangulate(tri)
        s = np.linalg.norm(P[pairs[:, 0]] - P[pairs[:, 1]], axis=1)
        sizes.append(s[np.isfinite(s)])
        used_tri = len(tri)
    sizes = np.concatenate(sizes) if sizes else np.zeros(0)
    source = "+".join(k for k, n in (("depth", used_depth), ("triangulation", used_tri)) if n) or "none"
    if len(sizes) < 2:
        return {"detections": used_depth + used_tri, "source": source, "square_size_mm": spacing * 1e3,
                "status": "the board is not found in enough solved views"}
    m_s, sigma = float(np.mean(sizes)), float(np.std(sizes, ddof=1))
    return {"m_s_mm": m_s * 1e3, "m_s_minus_s_mm": (m_s - spacing) * 1e3, "sigma_s_mm": sigma * 1e3,
            "delta_s_percent": abs(m_s - spacing) / spacing * 100, "detections": used_depth + used_tri,
            "square_size_mm": spacing * 1e3, "distances": int(len(sizes)), "source": source}


def reconstruction_accuracy(ds, preds, states, ground_truth: dict, max_points_per_view=20000) -> dict | None:
    """Median and 90 % distance (mm) from the reconstruction's points (every solved view's corrected depth,
    as in reconstruction.ply) to the true surface, where the dataset has its geometry: the simulator's
    scene, rebuilt from ground_truth.yaml's ``simulation`` entry. None without it."""
    sim = (ground_truth or {}).get("simulation")
    if not isinstance(sim, dict) or "seed" not in sim:
        return None
    import open3d as o3d

    from calib3r_graph.io.results import point_cloud
    from calib3r_graph.simulate import scene_from_simulation

    scene = scene_from_simulation(sim)
    pts = np.asarray(point_cloud(ds, preds, states, max_points_per_view=max_points_per_view).points)
    d = scene.scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy() * 1e3
    return {"median_mm": float(np.median(d)), "p90_mm": float(np.percentile(d, 90)), "points": int(len(d)),
            "surface": "the simulator's scene (ground_truth.yaml simulation)"}


def metric_scale_table(comparison: dict) -> str:
    """comparison.md's lines for the methods whose reconstruction has the paper's metric scale, or ''."""
    rows = [(m, r["metric_scale"]) for m, r in comparison.get("methods", {}).items()
            if "m_s_mm" in r.get("metric_scale", {})]
    if not rows:
        return ""
    lines = ["Metric reconstruction accuracy on the board (the paper's Table II; s = "
             f"{rows[0][1]['square_size_mm']:.2f} mm):", "",
             "| method | m_s − s (mm) | σ_s (mm) | δ_s (%) | views | from |", "|---|---|---|---|---|---|"]
    lines += [f"| {m} | {x['m_s_minus_s_mm']:+.3f} | {x['sigma_s_mm']:.3f} | {x['delta_s_percent']:.2f} | "
              f"{x['detections']} | {x['source']} |" for m, x in rows]
    return "\n".join(lines) + "\n"
