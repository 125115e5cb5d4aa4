"""Importers for public eye-in-hand recordings into calib3r-dataset/1.

* ``rwhe`` (RWHE-Calib, Ali et al., Sensors 2019): images ``01.png``... or ``im_XX.bmp``,
  ``RobotPosesVec.txt`` (one row-major 4x4 per line), ``squaresize.txt`` (or the misspelt
  ``sqauresize.txt``), board from ``--board`` (``COLSxROWS`` inner corners, or any spec of
  calib3r_graph.io.boards, e.g. ``charuco:COLSxROWS:SQUARE_M:MARKER_M``).
* ``tabb`` (Tabb & Ahmad Yousef, MVA 2017): ``imageXX.png``, ``robot_cali.txt`` (count, then
  4x4 matrices), ``calibration_object.txt`` (board and tile size).

Neither ships intrinsics: they are calibrated from the visible board (OpenCV,
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

from calib3r_graph.errors import InputError
from calib3r_graph.io import boards
from calib3r_graph.io.boards import Board
from calib3r_graph.io.dataset import Camera, write_dataset_yaml, write_robot_poses
from calib3r_graph.io.output import staged_directory

log = logging.getLogger(__name__)
IMAGE_SUFFIXES = (".png", ".bmp", ".jpg", ".jpeg")


@dataclass
class RawRecording:
    images: list  # [(frame id, path)]
    matrices: list  # 4x4 as published, one per image
    board: Board  # its size from the recording's files unless the spec gave one
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
    board = as_board(board)
    square = board.size if board.size else _read_square(src)
    return RawRecording([(f"{_frame_number(p):04d}", p) for p in imgs], mats, as_board(board, square), square, "rwhe")


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
    return RawRecording([(f"{_frame_number(p):04d}", p) for p in imgs], mats, as_board(board or cb, square), square,
                        "tabb")


def as_board(board, square_m=None) -> Board:
    """A Board from a spec string, a (cols, rows) of checkerboard inner corners, or a Board;
    ``square_m`` fills in a size the spec did not give."""
    if isinstance(board, str):
        board = boards.parse_board(board)
    elif not isinstance(board, Board):
        board = Board("checkerboard", int(board[0]), int(board[1]), None)
    return board if board.size or square_m is None else Board(board.kind, board.cols, board.rows, float(square_m),
                                                               board.marker, board.dictionary)


def read_gray(path: Path):
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise InputError(path, "unreadable image")
    return gray


def detect_all(images, board: Board, progress=True):
    """``({frame: (uv, ids)}, board used, (width, height))`` of the board in ``[(frame, path)]``.

    A checkerboard is tried as stated, then one corner smaller (recordings disagree on whether
    they count squares or inner corners); a ChArUco board without a dictionary gets the one
    its markers are found under."""
    if isinstance(images, RawRecording):
        images, board = images.images, images.board
    found, size = {}, None
    candidates = [board]
    if board.kind == "checkerboard":
        candidates.append(Board(board.kind, board.cols - 1, board.rows - 1, board.size))
    for cand in candidates:
        if cand.kind == "charuco":
            cand = boards.resolve_dictionary(cand, [read_gray(p) for _, p in images[:10]])
        for frame, path in tqdm(images, desc=cand.describe(), disable=None if progress else True, leave=False):
            gray = read_gray(path)
            size = gray.shape[::-1]
            hit = boards.detect(gray, cand)
            if hit is not None:
                found[frame] = hit
        if len(found) >= 3:
            return found, cand, size
        found = {}
    what = (f"the {board.cols}x{board.rows} chessboard" if board.kind == "checkerboard" else f"the {board.describe()}")
    raise InputError(images[0][1].parent, f"{what} is found in fewer than 3 images (wrong --board?)")


def _object_points(board: Board, ids):
    pts = boards.points(board)
    return (pts if ids is None else pts[ids]).astype(np.float32)


def calibrate_intrinsics(detections: dict, board: Board, size):
    """K, OPENCV distortion [k1, k2, p1, p2], RMS (px) and {frame: cam_T_board} from the board alone."""
    objs = [_object_points(board, ids) for _, ids in detections.values()]
    imgs = [uv.astype(np.float32) for uv, _ in detections.values()]
    flags = cv2.CALIB_FIX_K3
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(objs, imgs, size, None, None, flags=flags)
    poses = {f: gtsam.Pose3(gtsam.Rot3(cv2.Rodrigues(r)[0]), t.ravel()) for f, r, t in zip(detections, rvecs, tvecs)}
    return K, dist.ravel()[:4], rms, poses


def board_poses(detections: dict, board: Board, K, dist) -> dict:
    """{frame: cam_T_board} by PnP with known intrinsics."""
    out = {}
    for f, (uv, ids) in detections.items():
        ok, rvec, tvec = cv2.solvePnP(_object_points(board, ids).astype(np.float64), uv, K, np.asarray(dist, float))
        if ok:
            out[f] = gtsam.Pose3(gtsam.Rot3(cv2.Rodrigues(rvec)[0]), tvec.ravel())
    return out


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


def refine_intrinsics_with_robot(K, dist, size, detections, cam_T_board, base_T_ee, pattern):
    """K and distortion from a joint adjustment with the robot poses (pattern-ba with intrinsics).

    A board that is small and far in the image leaves focal length and board distance
    entangled in a board-only calibration; the robot's metric motion separates them.
    """
    from calib3r_graph.evaluation.pattern import Detection, opencv_hand_eye, pattern_ba
    from calib3r_graph.io.dataset import Dataset
    from calib3r_graph.solver.graph import NoiseOptions

    cam = Camera("cam0", "OPENCV", int(size[0]), int(size[1]), (K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist))
    ds = Dataset(Path("."), {"cam0": cam}, {f: base_T_ee[f] for f in detections}, pattern)
    dets = [Detection(f, uv.astype(np.float64), cam_T_board[f], 0.0, ids) for f, (uv, ids) in detections.items()]
    X0 = opencv_hand_eye(ds, dets, "park")
    fx, fy, cx, cy, *refined_dist = pattern_ba(ds, {"cam0": dets}, NoiseOptions(), {"cam0": X0}).intrinsics["cam0"]
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), np.array(refined_dist)


def import_recording(fmt: str, src, dst, board=None, progress=True) -> str:
    """``board``: a spec string, (cols, rows) inner corners, a Board or None (tabb reads its file)."""
    src, dst = Path(src), Path(dst)
    if not src.is_dir():
        raise InputError(src, "no such directory")
    rec = read_rwhe(src, board) if fmt == "rwhe" else read_tabb(src, board)
    corners, board_used, size = detect_all(rec.images, rec.board, progress)
    K, dist, rms, cam_T_board = calibrate_intrinsics(corners, board_used, size)
    mats = {f: m for (f, _), m in zip(rec.images, rec.matrices)}
    (unit, direction), _, residuals = choose_convention(mats, cam_T_board)
    # The chosen convention for every frame (also those where the board was not found).
    base_T_ee = {f: apply_convention(M, unit, direction) for f, M in mats.items()}
    pattern = boards.to_pattern(board_used)
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
             f"  intrinsics from the {board_used.describe()} in {len(corners)} images: "
             f"fx {K_board[0, 0]:.1f} fy {K_board[1, 1]:.1f} cx {K_board[0, 2]:.1f} cy {K_board[1, 2]:.1f}, "
             f"RMS {rms:.3f} px",
             f"  refined with the robot's metric motion (pattern-ba): fx {K[0, 0]:.1f} fy {K[1, 1]:.1f} "
             f"cx {K[0, 2]:.1f} cy {K[1, 2]:.1f}",
             *convention_lines(direction, unit, residuals)]
    return "\n".join(lines)


def convention_lines(direction: str, unit: str, residuals: dict) -> list:
    """The report of choose_convention: the one used, and the residuals of all four."""
    lines = [f"  robot poses: using '{direction}, {unit}' (AX=XB residual against the board's visual motion, "
             "rotation deg / translation mm):"]
    return lines + [f"    {'*' if k == f'{direction}, {unit}' else ' '} {k:42s} {r:8.3f} deg {t:10.2f} mm"
                    for k, (r, t) in residuals.items()]
