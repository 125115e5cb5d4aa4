"""Importers for public eye-in-hand recordings into calib3r-dataset/1.

* ``rwhe`` (RWHE-Calib, Ali et al., Sensors 2019): images ``01.png``... or ``im_XX.bmp``,
  ``RobotPosesVec.txt`` (one row-major 4x4 per line), ``squaresize.txt`` (or the misspelt
  ``sqauresize.txt``), board size from ``--board COLSxROWS`` (inner corners).
* ``tabb`` (Tabb & Ahmad Yousef, MVA 2017): ``imageXX.png``, ``robot_cali.txt`` (count, then
  4x4 matrices), ``calibration_object.txt`` (board and tile size).

Neither ships intrinsics: they are calibrated from the visible chessboard (OpenCV,
OPENCV model). Documentation about pose direction and units is not trusted: the robot
motions are compared with the visual motions of the board (PnP) — AX = XB is solved for
each convention (as given / inverted x metres / millimetres) and the one whose residual
is smallest is used, and printed.
"""

import logging
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import cv2
import gtsam
import numpy as np
from tqdm import tqdm

from calib3r_graph.dataset import Camera, write_dataset_yaml, write_robot_poses
from calib3r_graph.errors import InputError
from calib3r_graph.output import staged_directory

log = logging.getLogger(__name__)
IMAGE_SUFFIXES = (".png", ".bmp", ".jpg", ".jpeg")


@dataclass
class RawRecording:
    images: list  # [(frame id, path)]
    matrices: list  # 4x4 as published, one per image
    board: tuple  # inner corners (cols, rows)
    square_m: float
    source: str


def _frame_number(p: Path):
    m = re.search(r"(\d+)$", p.stem)
    return int(m.group(1)) if m else None


def _images(src: Path, pattern=None):
    imgs = [p for p in src.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and _frame_number(p) is not None
            and (pattern is None or re.fullmatch(pattern, p.stem))]
    return sorted(imgs, key=_frame_number)


def _read_square(src: Path) -> float:
    for name in ("squaresize.txt", "sqauresize.txt", "SquareSize.txt"):
        f = src / name
        if f.is_file():
            txt = f.read_text()
            m = re.search(r"([\d.]+)\s*(mm|m)?", txt)
            if not m:
                raise InputError(f, "no square size in it")
            v = float(m.group(1))
            return v / 1000 if (m.group(2) == "mm" or v > 1) else v
    raise InputError(src / "squaresize.txt", "missing (square size of the chessboard)")


def read_rwhe(src: Path, board=None) -> RawRecording:
    pose_file = src / "RobotPosesVec.txt"
    if not pose_file.is_file():
        raise InputError(pose_file, "missing (rwhe recordings have RobotPosesVec.txt)")
    mats = []
    for i, line in enumerate(pose_file.read_text().splitlines(), 1):
        if line.strip():
            try:
                v = np.array([float(x) for x in line.split()])
            except ValueError:
                raise InputError(pose_file, "not numbers", f"line {i}") from None
            if v.size != 16:
                raise InputError(pose_file, f"expected 16 numbers, got {v.size}", f"line {i}")
            mats.append(v.reshape(4, 4))
    imgs = _images(src)
    if len(imgs) != len(mats):
        raise InputError(src, f"{len(imgs)} images but {len(mats)} poses in RobotPosesVec.txt")
    if board is None:
        raise InputError("--board", "rwhe recordings need the board's inner corners, e.g. --board 28x17")
    return RawRecording([(f"{_frame_number(p):04d}", p) for p in imgs], mats, board, _read_square(src), "rwhe")


def read_tabb(src: Path, board=None) -> RawRecording:
    pose_file = src / "robot_cali.txt"
    if not pose_file.is_file():
        raise InputError(pose_file, "missing (tabb recordings have robot_cali.txt)")
    nums = pose_file.read_text().split()
    try:
        n = int(float(nums[0]))
        vals = np.array([float(x) for x in nums[1:]])
    except (ValueError, IndexError):
        raise InputError(pose_file, "expected a pose count and then 4x4 matrices") from None
    if vals.size != 16 * n:
        raise InputError(pose_file, f"pose count {n} but {vals.size / 16:g} matrices")
    mats = list(vals.reshape(n, 4, 4))
    imgs = _images(src, r"image\d+")
    if len(imgs) != n:
        raise InputError(src, f"{len(imgs)} images but {n} poses in robot_cali.txt")
    obj = src / "calibration_object.txt"
    square, cb = 0.0285, (8, 6)
    if obj.is_file():
        txt = obj.read_text()
        m = re.search(r"([\d.]+)\s*mm", txt)
        square = float(m.group(1)) / 1000 if m else square
        m = re.search(r"(\d+)\s*x\s*(\d+)", txt)
        cb = (int(m.group(1)), int(m.group(2))) if m else cb
    return RawRecording([(f"{_frame_number(p):04d}", p) for p in imgs], mats, board or cb, square, "tabb")


def detect_all(rec: RawRecording, progress=True):
    """Chessboard corners per frame; tries the stated board, then the board one corner smaller
    (recordings disagree on whether they count squares or inner corners)."""
    found, size = {}, None
    for cols, rows in (rec.board, (rec.board[0] - 1, rec.board[1] - 1)):
        for frame, path in tqdm(rec.images, desc=f"chessboard {cols}x{rows}", disable=None if progress else True, leave=False):
            gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                raise InputError(path, "unreadable image")
            size = gray.shape[::-1]
            ok, c = cv2.findChessboardCornersSB(gray, (cols, rows), flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
            if ok:
                found[frame] = c.reshape(-1, 2)
        if len(found) >= 3:
            return found, (cols, rows), size
        found = {}
    raise InputError(rec.images[0][1].parent, f"the {rec.board[0]}x{rec.board[1]} chessboard is found in fewer "
                                               "than 3 images (wrong --board?)")


def calibrate_intrinsics(corners: dict, board, square, size):
    obj = np.c_[np.mgrid[0:board[0], 0:board[1]].T.reshape(-1, 2) * square, np.zeros(board[0] * board[1])]
    objs = [obj.astype(np.float32)] * len(corners)
    imgs = [c.astype(np.float32) for c in corners.values()]
    flags = cv2.CALIB_FIX_K3
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(objs, imgs, size, None, None, flags=flags)
    poses = {f: gtsam.Pose3(gtsam.Rot3(cv2.Rodrigues(r)[0]), t.ravel()) for f, r, t in zip(corners, rvecs, tvecs)}
    return K, dist.ravel()[:4], rms, poses


def apply_convention(M, unit: str, direction: str) -> gtsam.Pose3:
    """A published 4x4 as base_T_ee in metres under a convention (unit m|mm, 'as given...'|'inverted...')."""
    from calib3r_graph.geometry import project_to_so3

    M = np.array(M, dtype=float)
    M[:3, 3] *= 1e-3 if unit == "mm" else 1.0
    M[:3, :3] = project_to_so3(M[:3, :3])  # published matrices carry rounding
    return gtsam.Pose3(M) if direction.startswith("as") else gtsam.Pose3(M).inverse()


def choose_convention(mats: dict, cam_T_board: dict):
    """(name, {frame: base_T_ee Pose3 in metres}, residuals) of the convention that makes AX = XB hold best."""
    from calib3r_graph.geometry import hand_eye_rotation

    frames = sorted(cam_T_board)
    results = {}
    for unit in ("m", "mm"):
        for direction in ("as given (base_T_ee)", "inverted (file holds ee_T_base)"):
            E = {f: apply_convention(mats[f], unit, direction) for f in frames}
            C = {f: cam_T_board[f].inverse() for f in frames}  # board_T_cam: camera in the board frame
            pairs = [(a, b) for i, a in enumerate(frames) for b in frames[i + 1:]]
            A = [E[a].between(E[b]) for a, b in pairs]
            B = [C[a].between(C[b]) for a, b in pairs]
            rot = [(gtsam.Rot3.Logmap(x.rotation()), gtsam.Rot3.Logmap(y.rotation())) for x, y in zip(A, B)
                   if np.linalg.norm(gtsam.Rot3.Logmap(y.rotation())) > np.radians(2)]
            if len(rot) < 2:
                raise InputError("robot poses", "fewer than two rotating robot motions: the convention cannot be checked")
            R_X, rot_res = hand_eye_rotation(*map(np.array, zip(*rot)))
            M_ = np.vstack([x.rotation().matrix() - np.eye(3) for x in A])
            rhs = np.concatenate([R_X @ y.translation() - x.translation() for x, y in zip(A, B)])
            t, *_ = np.linalg.lstsq(M_, rhs, rcond=None)
            t_res = float(np.sqrt(np.mean((M_ @ t - rhs) ** 2)) * 1e3)
            results[(unit, direction)] = (rot_res, t_res, E)
    best = min(results, key=lambda k: (results[k][0] > 2 * min(r[0] for r in results.values()) + 0.05, results[k][1]))
    return best, results[best][2], {f"{d}, {u}": (r[0], r[1]) for (u, d), r in results.items()}


def refine_intrinsics_with_robot(K, dist, size, corners, cam_T_board, base_T_ee, pattern):
    """K and distortion from a joint adjustment with the robot poses (pattern-ba with intrinsics).

    A board that is small and far in the image leaves focal length and board distance
    entangled in a board-only calibration; the robot's metric motion separates them.
    """
    from calib3r_graph.dataset import Dataset
    from calib3r_graph.graph import NoiseOptions
    from calib3r_graph.pattern import Detection, opencv_hand_eye, pattern_ba

    cam = Camera("cam0", "OPENCV", int(size[0]), int(size[1]), (K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist))
    ds = Dataset(Path("."), {"cam0": cam}, {f: base_T_ee[f] for f in corners}, pattern)
    dets = [Detection(f, c.astype(np.float64), cam_T_board[f], 0.0) for f, c in corners.items()]
    X0 = opencv_hand_eye(ds, dets, "park")
    fx, fy, cx, cy, *refined_dist = pattern_ba(ds, {"cam0": dets}, NoiseOptions(), {"cam0": X0}).intrinsics["cam0"]
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), np.array(refined_dist)


def import_recording(fmt: str, src, dst, board=None, progress=True) -> str:
    src, dst = Path(src), Path(dst)
    if not src.is_dir():
        raise InputError(src, "no such directory")
    rec = read_rwhe(src, board) if fmt == "rwhe" else read_tabb(src, board)
    corners, board_used, size = detect_all(rec, progress)
    K, dist, rms, cam_T_board = calibrate_intrinsics(corners, board_used, rec.square_m, size)
    mats = {f: m for (f, _), m in zip(rec.images, rec.matrices)}
    (unit, direction), _, residuals = choose_convention(mats, cam_T_board)
    # The chosen convention for every frame (also those where the board was not found).
    base_T_ee = {f: apply_convention(M, unit, direction) for f, M in mats.items()}
    pattern = {"type": "checkerboard", "inner_corners": [int(board_used[0]), int(board_used[1])],
               "square_size": float(rec.square_m)}
    K_board = K.copy()
    K, dist = refine_intrinsics_with_robot(K, dist, size, corners, cam_T_board, base_T_ee, pattern)
    cam = Camera("cam0", "OPENCV", int(size[0]), int(size[1]), tuple(float(x) for x in
                 (K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist)))
    with staged_directory(dst) as stage:
        (stage / "images" / "cam0").mkdir(parents=True)
        for f, p in rec.images:
            if p.suffix.lower() == ".png":
                shutil.copyfile(p, stage / "images" / "cam0" / f"{f}.png")
            else:
                cv2.imwrite(str(stage / "images" / "cam0" / f"{f}.png"), cv2.imread(str(p), cv2.IMREAD_COLOR))
        write_robot_poses(stage / "robot_poses.csv", base_T_ee, unit="m")
        write_dataset_yaml(stage, [cam], unit="m", pattern=pattern,
                           extra={"source": {"format": fmt, "path": str(src), "pose_convention": f"{direction}, {unit}",
                                             "intrinsics_rms_px": float(rms),
                                             "board_found_in": len(corners)}})
    lines = [f"imported {len(rec.images)} frames of {src} ({fmt}) into {dst}",
             f"  intrinsics from the {board_used[0]}x{board_used[1]} chessboard in {len(corners)} images: "
             f"fx {K_board[0, 0]:.1f} fy {K_board[1, 1]:.1f} cx {K_board[0, 2]:.1f} cy {K_board[1, 2]:.1f}, "
             f"RMS {rms:.3f} px",
             f"  refined with the robot's metric motion (pattern-ba): fx {K[0, 0]:.1f} fy {K[1, 1]:.1f} "
             f"cx {K[0, 2]:.1f} cy {K[1, 2]:.1f}",
             f"  robot poses: using '{direction}, {unit}' (AX=XB residual against the board's visual motion, "
             "rotation deg / translation mm):"]
    lines += [f"    {'*' if k == f'{direction}, {unit}' else ' '} {k:42s} {r:8.3f} deg {t:10.2f} mm"
              for k, (r, t) in residuals.items()]
    return "\n".join(lines)
