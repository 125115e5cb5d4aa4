"""The views of a solve result as the dense step needs them: each view's working grid (the image
resized to a reduced resolution, undistorted onto a pinhole grid with the same, scaled K), its solved
pose ``base_T_cam`` and the robot chain's pose ``base_T_ee · ee_T_cam``."""

import csv
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import gtsam
import numpy as np

from calib3r_graph.errors import InputError
from calib3r_graph.io.dataset import ee_T_cam_by_camera
from calib3r_graph.io.predictions import split_view_id, view_id

log = logging.getLogger(__name__)


@dataclass
class DenseView:
    vid: str
    camera: str
    frame: str
    base_T_cam: np.ndarray  # 4x4, the solve's pose of the view (trajectory.csv)
    chain_T_cam: np.ndarray  # 4x4, base_T_ee[frame] @ ee_T_cam[camera]: where the robot puts the camera
    K: np.ndarray  # 3x3 of the working grid (pinhole)
    size: tuple  # (width, height) of the working grid
    scale: float  # working grid / image
    image_path: Path | None
    gray: np.ndarray | None = None  # (h, w) uint8 on the working grid, distorted like the image
    rgb: np.ndarray | None = None  # (h, w, 3) uint8, undistorted onto the pinhole grid K
    K_raw: np.ndarray = None  # K of the resized but still distorted image (for rectification with dist)
    dist: np.ndarray = field(default_factory=lambda: np.zeros(4))


@dataclass
class SolveResult:
    """What ``solve`` wrote that the dense step reads."""

    base_T_cam: dict  # view -> 4x4
    ee_T_cam: dict  # camera -> 4x4
    predictions: str | None
    dir: Path


def read_result(result_dir) -> SolveResult:
    """calibration.json (ee_T_cam) and trajectory.csv (each view's base_T_cam) of a solve; a folder
    without them is a one-line error that says to solve first."""
    d = Path(result_dir)
    if not d.is_dir():
        raise InputError(d, "no such result folder (run 'calib3r-graph solve DATASET --out DIR' first)")
    cal_path, traj_path = d / "calibration.json", d / "trajectory.csv"
    for p in (cal_path, traj_path):
        if not p.is_file():
            raise InputError(p, "missing: this folder holds no solve result (run 'calib3r-graph solve DATASET "
                                f"--out {d}' first)")
    try:
        cal = json.loads(cal_path.read_text())
        ee_T_cam = {c: T.matrix() for c, T in ee_T_cam_by_camera(cal["cameras"]).items()}
    except (ValueError, KeyError, TypeError) as e:
        raise InputError(cal_path, f"not a calibration.json written by solve ({type(e).__name__}: {e})") from None
    poses = {}
    rows = list(csv.reader(traj_path.read_text().splitlines()))
    if not rows or rows[0] != ["camera", "frame", "x", "y", "z", "qx", "qy", "qz", "qw"]:
        raise InputError(traj_path, "header must be 'camera,frame,x,y,z,qx,qy,qz,qw'", "row 1")
    for n, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        try:
            x, y, z, qx, qy, qz, qw = map(float, row[2:9])
        except (ValueError, IndexError):
            raise InputError(traj_path, "expected camera, frame and 7 numbers", f"row {n}") from None
        poses[view_id(row[0], row[1])] = gtsam.Pose3(gtsam.Rot3.Quaternion(qw, qx, qy, qz),
                                                     np.array([x, y, z])).matrix()
    if not poses:
        raise InputError(traj_path, "no views")
    return SolveResult(poses, ee_T_cam, cal.get("predictions"), d)


def working_scale(width: int, height: int, max_side: int) -> float:
    return min(1.0, max_side / max(width, height))


def scaled_K(K: np.ndarray, s: float) -> np.ndarray:
    """K of an image resized by ``s`` (OpenCV pixel centres: (u + 0.5) s - 0.5)."""
    Ks = K.copy()
    Ks[:2] *= s
    Ks[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    Ks[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    return Ks


def dense_views(ds, result: SolveResult, max_side: int, ee_T_cam: dict | None = None) -> dict:
    """{view: DenseView} for every solved view whose camera and frame are in the dataset (images not
    loaded yet). ``ee_T_cam`` overrides the result's (for the disagreement sweep)."""
    ee = ee_T_cam or result.ee_T_cam
    out = {}
    for v, T in sorted(result.base_T_cam.items()):
        cam_name, frame = split_view_id(v)
        if cam_name not in ds.cameras or frame not in ds.base_T_ee or cam_name not in ee:
            log.warning("dense: %s is in the result but not in the dataset; skipped", v)
            continue
        cam = ds.cameras[cam_name]
        s = working_scale(cam.width, cam.height, max_side)
        size = (int(round(cam.width * s)), int(round(cam.height * s)))
        K = scaled_K(cam.K, s)
        out[v] = DenseView(v, cam_name, frame, np.asarray(T), ds.base_T_ee[frame].matrix() @ ee[cam_name], K, size,
                           s, ds.image_path(cam_name, frame), K_raw=K.copy(), dist=cam.dist)
    return out


def load_images(view: DenseView) -> str | None:
    """Reads the view's image onto its working grid; returns why it cannot, or None."""
    if view.image_path is None:
        return "no image"
    img = cv2.imread(str(view.image_path), cv2.IMREAD_COLOR)
    if img is None:
        return f"{view.image_path}: not a readable image"
    small = cv2.resize(img, view.size, interpolation=cv2.INTER_AREA) if view.scale < 1 else img
    if np.any(view.dist):
        small_u = cv2.undistort(small, view.K_raw, view.dist)
    else:
        small_u = small
    view.gray = cv2.cvtColor(small, cv2.COLOR_BGR2GRAY)
    view.rgb = np.ascontiguousarray(small_u[:, :, ::-1])
    return None
