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
is smallest is used, and printed (choose_convention); when even that one leaves far more than
the detections' own noise allows, the import is refused. A board that looks the same turned
by 180° has each image's corner order resolved against the robot's motion first
(board_turns.resolve_turns).
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
from calib3r_graph.io import board_turns, boards
from calib3r_graph.io.boards import Board
from calib3r_graph.io.dataset import opencv_camera, write_dataset_yaml, write_robot_poses
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


def calibrate_intrinsics(detections: dict, board: Board, size, with_sigma: bool = False):
    """K, OPENCV distortion [k1, k2, p1, p2], RMS (px) and {frame: cam_T_board} from the board alone;
    ``with_sigma``: and the 1-sigma of fx, fy, cx, cy (px; OpenCV's stdDeviationsIntrinsics)."""
    objs = [_object_points(board, ids) for _, ids in detections.values()]
    imgs = [uv.astype(np.float32) for uv, _ in detections.values()]
    flags = cv2.CALIB_FIX_K3
    rms, K, dist, rvecs, tvecs, std, *_ = cv2.calibrateCameraExtended(objs, imgs, size, None, None, flags=flags)
    poses = {f: gtsam.Pose3(gtsam.Rot3(cv2.Rodrigues(r)[0]), t.ravel()) for f, r, t in zip(detections, rvecs, tvecs)}
    return (K, dist.ravel()[:4], rms, poses) + ((tuple(float(x) for x in std.ravel()[:4]),) if with_sigma else ())


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


# Directions as the report names them; --direction's values map onto them.
DIRECTIONS = {"base_T_ee": "as given (base_T_ee)", "ee_T_base": "inverted (file holds ee_T_base)"}
DIRECTION_KEYS = {v: k for k, v in DIRECTIONS.items()}
# When is a convention's AX = XB fit "far above what a board allows"? Its residuals are compared with
# what a correct convention leaves with these detections (_fit's expectation: each view's PnP
# covariance from its own corner noise, plus the robot's nominal noise). Measured on import
# rwhe/tabb's detections (residual, expectation, ratio; rotation, translation), the correct convention:
# rwhe_kuka_1 0.072 / 0.050 deg, 1.25 / 0.30 mm (1.5x, 4.1x); rwhe_kuka_2 0.059 / 0.049 deg,
# 0.39 / 0.28 mm (1.2x, 1.4x); tabb_ds1 0.74 / 0.22 deg, 16.0 / 4.1 mm (3.4x, 3.9x): robots err a
# little beyond their nominal noise. The same images paired one off, in name order (1, 10, 11, ...,
# 2) or at random leave 40-780x in rotation (8.8-38 deg) and 65-990x in translation (66-520 mm); a
# third of the boards turned by 180 deg and not resolved 395-1950x (84-97 deg); the wrong unit alone,
# on the translation-poor rwhe_kuka_2, 17x (4.7 mm). FIT_RATIO sits in the gap, an order of
# magnitude above the expectation, in rotation. Translation gets a wider factor: the expectation
# takes the robot's nominal 0.2 mm, but an arm's flange position errs by its absolute accuracy
# (0.5-3 mm on industrial arms, several times the nominal; tabb_ds1 already leaves 3.9x), while its
# orientation stays within a few hundredths of a degree; mispaired images still leave >= 65x.
FIT_RATIO = 10.0
FIT_RATIO_TRANSLATION = 30.0
# Whatever the expectation (a tiny, far board expects a lot): a robot's orientation and the pose of a
# board seen at all are never degrees off, so a correct convention never leaves 5 deg of mean
# rotation residual nor 100 mm of translation (the real ones: <= 0.74 deg, 16 mm; mispaired >= 8.8 deg).
CEILING_DEG, CEILING_MM = 5.0, 100.0


@dataclass
class Convention:
    unit: str  # m | mm
    direction: str  # a value of DIRECTIONS
    residuals: dict  # "direction, unit" -> (rotation deg, translation mm) of AX = XB, for each one tried
    expected: tuple  # (deg, mm) a correct convention leaves with these detections
    turns: board_turns.Turns  # the board's turns resolved under this convention
    forced: bool = False

    @property
    def name(self) -> str:
        return f"{self.direction}, {self.unit}"


def _fit(E: dict, P: dict, cov: dict, frames):
    """AX = XB of the robot's and the board's relative motions: ((rotation deg, translation mm) left
    after the least-squares X, (deg, mm) a correct convention would leave).

    Residuals: the mean of |alpha - R_X beta| (rotation vectors, pairs rotating > 2 deg), and the RMS
    per component of (R_A - I) t_X - (R_X t_B - t_A). The expectation: B_ij = P_i P_j^-1 perturbed
    by the views' PnP noise xi_i, xi_j is B_ij Exp(Ad(P_j)(xi_i - xi_j)), so its covariance is
    Ad(P_j) (S_i + S_j) Ad(P_j)^T; with the robot's nominal noise on both poses of A."""
    from calib3r_graph.geometry import hand_eye_rotation

    pairs = [(a, b) for i, a in enumerate(frames) for b in frames[i + 1:]]
    A = [E[a].between(E[b]) for a, b in pairs]
    B = [P[a].compose(P[b].inverse()) for a, b in pairs]
    var = []
    for a, b in pairs:
        Ad = P[b].AdjointMap()
        S = Ad @ (cov[a] + cov[b]) @ Ad.T
        var.append((np.trace(S[:3, :3]) + 6 * board_turns.ROBOT_SIGMA_RAD ** 2,
                    np.trace(S[3:, 3:]) + 6 * board_turns.ROBOT_SIGMA_M ** 2))
    var = np.array(var)
    alphas = np.array([gtsam.Rot3.Logmap(x.rotation()) for x in A])
    betas = np.array([gtsam.Rot3.Logmap(y.rotation()) for y in B])
    rotating = np.linalg.norm(betas, axis=1) > np.radians(2)
    if rotating.sum() < 2:
        raise InputError("robot poses", "fewer than two rotating robot motions: the convention cannot be checked")
    R_X, rot_res = hand_eye_rotation(alphas[rotating], betas[rotating])
    M_ = np.vstack([x.rotation().matrix() - np.eye(3) for x in A])
    rhs = np.concatenate([R_X @ y.translation() - x.translation() for x, y in zip(A, B)])
    t, *_ = np.linalg.lstsq(M_, rhs, rcond=None)
    t_res = float(np.sqrt(np.mean((M_ @ t - rhs) ** 2)) * 1e3)
    expected = (float(np.degrees(np.mean(np.sqrt(var[rotating, 0])))), float(np.sqrt(np.mean(var[:, 1]) / 3) * 1e3))
    return (rot_res, t_res), expected


def fits(residual, expected) -> bool:
    """Whether an AX = XB residual (deg, mm) is what a correct convention leaves (see FIT_RATIO)."""
    return (residual[0] <= min(FIT_RATIO * expected[0], CEILING_DEG)
            and residual[1] <= min(FIT_RATIO_TRANSLATION * expected[1], CEILING_MM))


def choose_convention(mats: dict, cam_T_board: dict, covariances: dict, board: Board, unit=None, direction=None,
                      poses="robot poses", images="the images", pairing="in order") -> Convention:
    """The pose convention (unit m|mm, direction) under which the robot's motion and the board's
    agree (AX = XB), with the board's turns resolved under each (board_turns.resolve_turns).

    ``unit``/``direction`` (a key of DIRECTIONS) force them: the choice is then among the rest
    only, but the fit is still checked. Raises InputError (naming ``poses``, ``images`` and how they
    were paired) when the best convention leaves a residual far above what a correct one would
    (``fits``), and when the board's turns cannot be told apart in some images."""
    frames = sorted(f for f in cam_T_board if f in mats)
    results = {}
    for u in ("m", "mm"):
        for d in DIRECTIONS.values():
            E = {f: apply_convention(mats[f], u, d) for f in frames}
            turned = board_turns.resolve_turns(board, cam_T_board, E, covariances)
            _, P = unturned({}, {f: cam_T_board[f] for f in frames}, board, turned)
            results[(u, d)] = (*_fit(E, P, covariances, frames), turned)

    def best_of(keys):
        rmin = min(results[k][0][0] for k in keys)
        return min(keys, key=lambda k: (results[k][0][0] > 2 * rmin + 0.05, results[k][0][1]))
    allowed = [k for k in results
               if (unit is None or k[0] == unit) and (direction is None or k[1] == DIRECTIONS[direction])]
    best = best_of(allowed)
    res, expected, turned = results[best]
    conv = Convention(best[0], best[1], {f"{d}, {u}": r[0] for (u, d), r in results.items()}, expected, turned,
                      len(allowed) < len(results))
    if not fits(res, expected):
        other = best_of(list(results))
        if other not in allowed and fits(*results[other][:2]):
            raise InputError(poses, f"the poses do not fit the board's motion in {images} with "
                                    f"{_forced(unit, direction)} ({res[0]:.2f} deg / {res[1]:.1f} mm of AX=XB "
                                    f"residual), but they do as '{other[1]}, {other[0]}' "
                                    f"({results[other][0][0]:.2f} deg / {results[other][0][1]:.1f} mm): check --unit "
                                    "and --direction")
        which = (f"with {_forced(unit, direction)}, " if conv.forced else "") + f"the best, '{conv.name}',"
        flipped = (f" ({board_turns.unresolved_message(board, turned)})" if turned.unresolved else
                   f" (the {board.describe()} looks the same turned by {360 // turned.n} deg: a ChArUco board removes "
                   "that doubt)" if turned.n > 1 else "")
        raise InputError(poses, f"no pose convention fits the board's motion in {images}: {which} leaves "
                                f"{res[0]:.2f} deg / {res[1]:.1f} mm of AX=XB residual where a correct one leaves "
                                f"about {expected[0]:.2f} deg / {expected[1]:.2f} mm with these detections. Likely "
                                f"causes, most likely first: images and poses mispaired (they were paired {pairing}); "
                                f"the board moved or flipped between images{flipped}; a wrong pose format "
                                "(--pose-format, or poses that are not the flange's)")
    if turned.unresolved:
        raise InputError("--board", board_turns.unresolved_message(board, turned))
    return conv


def _forced(unit, direction) -> str:
    return " and ".join(x for x in (direction and f"direction {direction}", unit and f"unit {unit}") if x) + " (forced)"


def unturned(detections: dict, cam_T_board: dict, board: Board, turned: "board_turns.Turns") -> tuple:
    """``({frame: (uv, ids)}, {frame: cam_T_board})`` renumbered as the board was really seen
    (boards.turn_detection), the poses turned to match."""
    dets = {f: (boards.turn_detection(board, uv, turned.turns.get(f, 0), turned.n), ids)
            for f, (uv, ids) in detections.items()}
    poses = {f: board_turns.unturn_pose(board, P, turned.turns.get(f, 0), turned.n) for f, P in cam_T_board.items()}
    return dets, poses


def refine_intrinsics_with_robot(K, dist, size, detections, cam_T_board, base_T_ee, pattern, with_sigma=False):
    """K and distortion from a joint adjustment with the robot poses (pattern-ba with intrinsics);
    ``with_sigma``: and the posterior 1-sigma of fx, fy, cx, cy (px; None if unobservable).

    A board that is small and far in the image leaves focal length and board distance
    entangled in a board-only calibration; the robot's metric motion separates them.
    """
    from calib3r_graph.evaluation.pattern import Detection, opencv_hand_eye, pattern_ba
    from calib3r_graph.io.dataset import Dataset
    from calib3r_graph.solver.graph import NoiseOptions

    cam = opencv_camera("cam0", size, K, dist)
    ds = Dataset(Path("."), {"cam0": cam}, {f: base_T_ee[f] for f in detections}, pattern)
    dets = [Detection(f, uv.astype(np.float64), cam_T_board[f], 0.0, ids) for f, (uv, ids) in detections.items()]
    X0 = opencv_hand_eye(ds, dets, "park")
    ba = pattern_ba(ds, {"cam0": dets}, NoiseOptions(), {"cam0": X0})
    fx, fy, cx, cy, *refined_dist = ba.intrinsics["cam0"]
    out = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), np.array(refined_dist)
    if not with_sigma:
        return out
    sigma = (ba.intrinsics_sigma or {}).get("cam0")
    return out + (tuple(float(x) for x in sigma[:4]) if sigma is not None and np.all(np.isfinite(sigma[:4])) else None,)


# The convention each format's own documentation states (tabb's "base-to-hand", in mm); the images decide.
DECLARED = {"rwhe": ("m", "base_T_ee"), "tabb": ("mm", "base_T_ee")}
POSE_FILES = {"rwhe": "RobotPosesVec.txt", "tabb": "robot_cali.txt"}


def import_recording(fmt: str, src, dst, board=None, progress=True, unit=None, direction=None) -> str:
    """``board``: a spec string, (cols, rows) inner corners, a Board or None (tabb reads its file);
    ``unit`` (m|mm) and ``direction`` (base_T_ee|ee_T_base) force the pose convention."""
    src, dst = Path(src), Path(dst)
    if not src.is_dir():
        raise InputError(src, "no such directory")
    rec = read_rwhe(src, board) if fmt == "rwhe" else read_tabb(src, board)
    corners, board_used, size = detect_all(rec.images, rec.board, progress)
    K, dist, rms, cam_T_board, board_sigma = calibrate_intrinsics(corners, board_used, size, with_sigma=True)
    mats = {f: m for (f, _), m in zip(rec.images, rec.matrices)}
    conv = choose_convention(mats, cam_T_board, board_turns.pose_covariances(board_used, corners, cam_T_board, K, dist),
                             board_used, unit, direction, src / POSE_FILES[fmt], f"the images of {src}",
                             "line by line with the images in the order of their numbers")
    unit, direction = conv.unit, conv.direction
    corners, cam_T_board = unturned(corners, cam_T_board, board_used, conv.turns)
    # The chosen convention for every frame (also those where the board was not found).
    base_T_ee = {f: apply_convention(M, unit, direction) for f, M in mats.items()}
    pattern = boards.to_pattern(board_used)
    K_board = K.copy()
    K, dist, refined_sigma = refine_intrinsics_with_robot(K, dist, size, corners, cam_T_board, base_T_ee, pattern,
                                                          with_sigma=True)
    # The intrinsics' own 1-sigma, for solve's total covariance (solver/camera_model.py): the joint
    # adjustment's posterior (the sigma of the values written), else the board calibration's.
    sigma = board_sigma if refined_sigma is None else refined_sigma
    cam = opencv_camera("cam0", size, K, dist, params_sigma=sigma)
    with staged_directory(dst) as stage:
        (stage / "images" / "cam0").mkdir(parents=True)
        for f, p in rec.images:
            if p.suffix.lower() == ".png":
                shutil.copyfile(p, stage / "images" / "cam0" / f"{f}.png")
            else:
                cv2.imwrite(str(stage / "images" / "cam0" / f"{f}.png"), cv2.imread(str(p), cv2.IMREAD_COLOR))
        write_robot_poses(stage / "robot_poses.csv", base_T_ee, unit="m")
        write_dataset_yaml(stage, [cam], unit="m", pattern=pattern,
                           extra={"source": {"format": fmt, "path": str(src), "pose_convention": conv.name,
                                             **turns_record(conv),
                                             "intrinsics_rms_px": float(rms),
                                             "board_found_in": len(corners)}})
    lines = [f"imported {len(rec.images)} frames of {src} ({fmt}) into {dst}",
             f"  intrinsics from the {board_used.describe()} in {len(corners)} images: "
             f"fx {K_board[0, 0]:.1f} fy {K_board[1, 1]:.1f} cx {K_board[0, 2]:.1f} cy {K_board[1, 2]:.1f}, "
             f"RMS {rms:.3f} px",
             f"  refined with the robot's metric motion (pattern-ba): fx {K[0, 0]:.1f} fy {K[1, 1]:.1f} "
             f"cx {K[0, 2]:.1f} cy {K[1, 2]:.1f}; 1-sigma {' '.join(f'{x:.2f}' for x in sigma)} px "
             "(params_sigma, propagated by solve)",
             *convention_lines(conv, *DECLARED[fmt], f"as the {fmt} format documents")]
    return "\n".join(lines)


def convention_lines(conv: Convention, unit: str, direction: str, declared: str) -> list:
    """The report of choose_convention: the one used (and how it was decided), the residuals of all
    four with what a correct one leaves, the board's turns, and a warning (also logged) when the
    convention used is not the declared ``unit``/``direction`` (``declared`` says who declared it)."""
    how = "forced, and checked" if conv.forced else "chosen"
    lines = [f"  robot poses: using '{conv.name}' ({how} by the AX=XB residual against the board's visual motion, "
             f"rotation deg / translation mm; a correct convention leaves about {conv.expected[0]:.3f} deg / "
             f"{conv.expected[1]:.2f} mm with these detections):"]
    lines += [f"    {'*' if k == conv.name else ' '} {k:42s} {r:8.3f} deg {t:10.2f} mm"
              for k, (r, t) in conv.residuals.items()]
    t = conv.turns
    if t.n > 1:
        lines.append(f"  board: looks the same turned by {360 // t.n} deg; "
                     + (f"{len(t.turned)} of {len(t.turns)} detections renumbered to agree with the robot's motion "
                        f"({', '.join(t.turned[:8])}{' ...' if len(t.turned) > 8 else ''})" if t.turned else
                        f"all {len(t.turns)} detections agree with the robot's motion as detected"))
    if (conv.unit, conv.direction) != (unit, DIRECTIONS[direction]):
        msg = (f"the poses fit the images as '{conv.name}', not as {direction} in {unit} ({declared}): "
               f"using '{conv.name}'")
        log.warning(msg)
        lines.append(f"  ! {msg}")
    return lines


def turns_record(conv: Convention) -> dict:
    """dataset.yaml's record of a board that looks the same turned (empty when it does not)."""
    t = conv.turns
    return {"board_turns": {"looks_the_same_turned_by_deg": 360 // t.n, "renumbered": t.turned}} if t.n > 1 else {}
