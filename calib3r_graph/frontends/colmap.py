"""Classical frontend on pycolmap (CPU): SIFT extraction with the dataset's intrinsics held
fixed, exhaustive matching with two-view geometric verification, incremental mapping.

What it hands the backend: for each registered view a sparse depth map from the
triangulated tracks (COLMAP's arbitrary but common unit; conf 0 elsewhere), matches
between views sharing tracks (top-k co-visibility by shared tracks), and COLMAP's poses
(``poses.csv``, world_T_cam in COLMAP units) usable as the solver's initialisation.

Pixel conventions: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), the
dataset contract (OpenCV) at (0, 0): intrinsics and keypoints are converted here, at the
boundary (a 0.5 px principal-point slip costs a constant rotation bias).
"""

import csv
import io
import logging
import shutil
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from calib3r_graph.errors import InputError, SolveError
from calib3r_graph.frontends.common import FULL_CONF_ANGLE_DEG, covisibility_edges
from calib3r_graph.io.output import atomic_write_text
from calib3r_graph.io.predictions import (PairMatches, ViewPrediction, read_poses_csv,  # noqa: F401
                                          save_predictions, view_id)

log = logging.getLogger(__name__)


def _colmap_params(camera) -> str:
    p = list(camera.params)
    p[2] += 0.5  # OpenCV -> COLMAP pixel centre convention
    p[3] += 0.5
    return ",".join(f"{x:.10g}" for x in p)


def run_colmap(ds, work: Path, max_features=2048, progress=True):
    """Features, matching and mapping; returns (largest reconstruction, image name -> view id)."""
    import pycolmap

    if not logging.getLogger("calib3r_graph").isEnabledFor(logging.DEBUG):
        pycolmap.logging.minloglevel = 2  # COLMAP's own INFO lines only with --debug
    db = work / "database.db"
    names = {}
    steps = tqdm(total=3, desc="colmap", disable=None if progress else True, leave=False)
    for cam in ds.cameras.values():
        imgs = []
        for f in ds.frames:
            p = ds.image_path(cam.name, f)
            if p is not None:
                imgs.append(f"{cam.name}/{p.name}")
                names[imgs[-1]] = view_id(cam.name, f)
        if not imgs:
            continue
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = cam.model
        reader.camera_params = _colmap_params(cam)
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.sift.max_num_features = max_features
        extraction.use_gpu = False
        pycolmap.extract_features(db, ds.root / "images", image_names=imgs, camera_mode=pycolmap.CameraMode.PER_FOLDER,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    if not names:
        raise InputError(ds.root / "images", "no images for the frames in robot_poses.csv")
    steps.update()
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    steps.update()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    opts.random_seed = 0
    recs = pycolmap.incremental_mapping(db, ds.root / "images", work / "sparse", opts)
    steps.update()
    steps.close()
    if not recs:
        raise SolveError("colmap: incremental mapping registered no images (too little texture or overlap)")
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    return rec, names


def cam_T_world(image) -> np.ndarray:
    """A registered pycolmap image's pose as a 4x4 cam_T_world (COLMAP units)."""
    cam_from_world = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    T = np.eye(4)
    T[:3] = cam_from_world.matrix()
    return T


def triangulation_angles(rec, point_ids, centres) -> np.ndarray:
    """Largest angle (rad) between the viewing rays of each 3D point's track.

    Depth from triangulation is only as good as this angle: far points seen from nearby
    cameras have small angles and uncertain depth, and get low confidence.
    """
    out = np.zeros(len(point_ids))
    for k, pid in enumerate(point_ids):
        p = rec.point3D(pid)
        rays = np.array([centres[el.image_id] for el in p.track.elements if el.image_id in centres]) - p.xyz
        if len(rays) < 2:
            continue
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        out[k] = np.arccos(np.clip((rays @ rays.T).min(), -1.0, 1.0))
    return out


def _undistort(camera, uv):
    if not np.any(camera.dist):
        return uv
    return cv2.undistortPoints(uv.reshape(-1, 1, 2), camera.K, camera.dist, P=camera.K).reshape(-1, 2)


def predict_colmap(ds, name="colmap", neighbours=6, max_features=2048, progress=True, keep_workspace=None):
    t0 = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix="calib3r-colmap-"))
    try:
        rec, names = run_colmap(ds, work, max_features, progress)
        views, poses, obs = {}, {}, {}  # obs: view -> {point3D_id: uv}
        centres = {i: rec.image(i).projection_center() for i in rec.reg_image_ids()}
        for image_id in rec.reg_image_ids():
            img = rec.image(image_id)
            vid = names.get(img.name)
            if vid is None:
                continue
            cam = ds.cameras[vid.split("/")[0]]
            T = cam_T_world(img)
            poses[vid] = np.linalg.inv(T)  # world_T_cam
            pts2d = [p for p in img.points2D if p.has_point3D()]
            if len(pts2d) < 10:
                continue
            uv = _undistort(cam, np.array([p.xy for p in pts2d]) - 0.5)
            ids = np.array([p.point3D_id for p in pts2d])
            xyz = np.array([rec.point3D(i).xyz for i in ids])
            z = (xyz @ T[:3, :3].T + T[:3, 3])[:, 2]
            # Confidence: full at >= 5 degrees of triangulation angle, less for far/narrow tracks.
            angle_conf = np.clip(triangulation_angles(rec, ids, centres) / np.radians(FULL_CONF_ANGLE_DEG), 0.05, 1.0)
            depth = np.zeros((cam.height, cam.width), np.float32)
            conf = np.zeros_like(depth)
            # Splat each track's depth onto the 2x2 pixels around its keypoint, so bilinear
            # sampling at the keypoint returns exactly that depth.
            x0, y0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
            ok = (z > 0) & (x0 >= 0) & (y0 >= 0) & (x0 < cam.width - 1) & (y0 < cam.height - 1)
            for dx in (0, 1):
                for dy in (0, 1):
                    depth[y0[ok] + dy, x0[ok] + dx] = z[ok]
                    conf[y0[ok] + dy, x0[ok] + dx] = angle_conf[ok]
            views[vid] = ViewPrediction(depth, conf, cam.K)
            obs[vid] = {int(i): u for i, u, good in zip(ids, uv, ok) if good}
        ids = sorted(views)
        shared = {}
        for i, a in enumerate(ids):
            for b in ids[i + 1:]:
                common = obs[a].keys() & obs[b].keys()
                if len(common) >= 20:
                    shared[(a, b)] = sorted(common)
        edges = covisibility_edges({e: len(c) for e, c in shared.items()}, ids, neighbours)
        pairs = []
        for a, b in edges:
            c = shared[(a, b)]
            pairs.append(PairMatches(a, b, np.array([obs[a][k] for k in c]), np.array([obs[b][k] for k in c]),
                                     np.ones(len(c))))
        if not pairs:
            raise SolveError("colmap: no two registered views share triangulated points")
        save_predictions(ds.root, name, views, pairs,
                         {"source": "calib3r-graph colmap (pycolmap incremental mapping, sparse depth from tracks)",
                          "metric_depth": False, "match_noise_px": 0.7, "registered": len(poses),
                          "images": len(names), "seconds": time.perf_counter() - t0,
                          "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error())})
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["view", *(f"T{i}{j}" for i in range(3) for j in range(4))])
        for v in sorted(poses):
            w.writerow([v, *(f"{x:.12g}" for x in poses[v][:3].ravel())])
        atomic_write_text(ds.root / "predictions" / name / "poses.csv", buf.getvalue())
        log.info("colmap frontend: %d/%d images registered, %d pairs, %.0f s", len(poses), len(names), len(pairs),
                 time.perf_counter() - t0)
        if keep_workspace:
            shutil.copytree(work, keep_workspace, dirs_exist_ok=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return name


def colmap_trajectory(ds, progress=False, max_features=2048) -> dict:
    """Only COLMAP's trajectory: {view: world_T_cam 4x4} of the registered images (temporary workspace)."""
    work = Path(tempfile.mkdtemp(prefix="calib3r-colmap-"))
    try:
        rec, names = run_colmap(ds, work, max_features, progress)
        out = {}
        for image_id in rec.reg_image_ids():
            img = rec.image(image_id)
            if img.name in names:
                out[names[img.name]] = np.linalg.inv(cam_T_world(img))
        return out
    finally:
        shutil.rmtree(work, ignore_errors=True)
