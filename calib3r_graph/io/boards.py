"""Calibration boards: spec parsing, the board's 3D points and detection in an image.

Four kinds, each written on the command line as a spec and in ``dataset.yaml`` as a
``pattern:`` block (:func:`to_pattern` / :func:`from_pattern` convert):

* ``checkerboard``: ``COLSxROWS[:SQUARE_M]``, inner corners (today's ``--board``);
  pattern ``{type: checkerboard, inner_corners: [c, r], square_size}``.
* ``charuco``: ``charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT]``, COLSxROWS counts squares;
  the ArUco dictionary (e.g. ``DICT_5X5_100``) is detected from the images when omitted.
  Pattern ``{type: charuco, squares: [c, r], square_size, marker_size, dictionary}``.
* ``circles``: ``circles:COLSxROWS:SPACING_M``, a symmetric grid, ``spacing`` between
  neighbouring centres; pattern ``{type: circles, grid: [c, r], spacing}``.
* ``asymmetric_circles``: ``acircles:COLSxROWS:SPACING_M``, OpenCV's asymmetric grid (COLS
  circles per row, rows offset by half a period); ``spacing`` is the distance between rows,
  circles in a row are 2·spacing apart. Pattern ``{type: asymmetric_circles, grid, spacing}``.

Board points lie in the board's z = 0 plane, in metres. A detection is ``(uv, ids)``: the
image points (distorted pixels, OpenCV's pixel-centre convention) and their indices into
:func:`points`; a ChArUco board is often seen partly, the others are found whole.
"""

import re
from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import gtsam
import numpy as np

from calib3r_graph.errors import InputError

KINDS = ("checkerboard", "charuco", "circles", "asymmetric_circles")
# Families tried when a ChArUco spec names no dictionary; the board's markers are ids
# 0..n-1, which every size of a family shares, so the smallest size that holds them is named.
ARUCO_FAMILIES = ("4X4", "5X5", "6X6", "7X7")
ARUCO_SIZES = (50, 100, 250, 1000)
ARUCO_OTHERS = ("DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_36h11", "DICT_APRILTAG_25h9", "DICT_APRILTAG_16h5")
MIN_CHARUCO_CORNERS = 6


@dataclass(frozen=True)
class Board:
    kind: str
    cols: int  # checkerboard: inner corners; charuco: squares; circles: circles per row
    rows: int
    size: float | None  # square side or circle spacing, metres (None: not known yet)
    marker: float | None = None  # charuco marker side, metres
    dictionary: str | None = None  # charuco: e.g. DICT_5X5_100; None = detect

    def describe(self) -> str:
        extra = f", markers {self.marker * 1e3:g} mm, {self.dictionary or 'dictionary auto'}" if self.marker else ""
        size = f" {self.size * 1e3:g} mm" if self.size else ""
        return f"{self.kind} {self.cols}x{self.rows}{size}{extra}"


def _grid(text, where):
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m:
        raise InputError(where, f"'{text}' is not COLSxROWS, e.g. 9x6")
    return int(m.group(1)), int(m.group(2))


def _metres(text, what, where):
    try:
        v = float(text)
    except ValueError:
        raise InputError(where, f"{what} '{text}' is not a number of metres") from None
    if not 0 < v < 5:
        raise InputError(where, f"{what} {v:g} must be a positive number of metres (e.g. 0.03 for 30 mm)")
    return v


def parse_board(spec: str, where="--board") -> Board:
    """A command-line board spec -> Board (see the module doc for the forms)."""
    parts = [p.strip() for p in str(spec).split(":")]
    kind = parts[0].lower()
    if re.fullmatch(r"\d+\s*[xX]\s*\d+", parts[0]):
        kind, parts = "checkerboard", ["checkerboard"] + parts
    aliases = {"checkerboard": "checkerboard", "chessboard": "checkerboard", "charuco": "charuco",
               "circles": "circles", "acircles": "asymmetric_circles", "asymmetric_circles": "asymmetric_circles"}
    if kind not in aliases:
        raise InputError(where, f"'{spec}' is not a board: COLSxROWS[:SQUARE_M], charuco:COLSxROWS:SQUARE_M:MARKER_M"
                                "[:DICT], circles:COLSxROWS:SPACING_M or acircles:COLSxROWS:SPACING_M")
    kind = aliases[kind]
    if len(parts) < 2:
        raise InputError(where, f"'{spec}' needs COLSxROWS")
    cols, rows = _grid(parts[1], where)
    if kind == "checkerboard":
        if len(parts) > 3:
            raise InputError(where, f"'{spec}': a checkerboard is COLSxROWS[:SQUARE_M]")
        board = Board(kind, cols, rows, _metres(parts[2], "square size", where) if len(parts) == 3 else None)
    elif kind == "charuco":
        if len(parts) not in (4, 5):
            raise InputError(where, f"'{spec}': a ChArUco board is charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT]")
        board = Board(kind, cols, rows, _metres(parts[2], "square size", where),
                      _metres(parts[3], "marker size", where), _dictionary_name(parts[4], where) if len(parts) == 5
                      else None)
    else:
        if len(parts) != 3:
            raise InputError(where, f"'{spec}': a circle grid is {parts[0]}:COLSxROWS:SPACING_M")
        board = Board(kind, cols, rows, _metres(parts[2], "spacing", where))
    _check(board, where)
    return board


def _dictionary_name(name, where) -> str:
    key = str(name).upper()
    key = key if key.startswith("DICT_") else "DICT_" + key
    for n in dir(cv2.aruco):
        if n.startswith("DICT_") and n.upper() == key:
            return n
    raise InputError(where, f"unknown ArUco dictionary '{name}' (e.g. DICT_4X4_50, DICT_5X5_100, DICT_6X6_250)")


def _check(board: Board, where):
    low = 3 if board.kind == "charuco" else 2
    if board.cols < low or board.rows < low:
        raise InputError(where, f"a {board.kind} needs at least {low}x{low}")
    if board.kind == "charuco" and board.marker is not None and board.size is not None and board.marker >= board.size:
        raise InputError(where, f"the marker ({board.marker:g} m) must be smaller than the square ({board.size:g} m)")


def from_pattern(pattern: dict, path="dataset.yaml") -> Board:
    """A ``dataset.yaml`` pattern block -> Board, validated (raises InputError naming ``path``)."""
    where = path
    if not isinstance(pattern, dict):
        raise InputError(where, "must be a mapping with a type", "pattern")
    kind = pattern.get("type")
    if kind not in KINDS:
        raise InputError(where, f"unsupported pattern type '{kind}' (expected one of {', '.join(KINDS)})",
                         "pattern.type")
    key = {"checkerboard": "inner_corners", "charuco": "squares"}.get(kind, "grid")
    grid = pattern.get(key)
    if not (isinstance(grid, list) and len(grid) == 2 and all(isinstance(c, int) and not isinstance(c, bool)
                                                              for c in grid)):
        raise InputError(where, f"{key} must be [columns, rows], integers", f"pattern.{key}")
    size_key = "spacing" if "circles" in kind else "square_size"
    numbers = {k: pattern.get(k) for k in (size_key, "marker_size") if k == size_key or kind == "charuco"}
    for k, v in numbers.items():
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not v > 0:
            raise InputError(where, f"{k} must be a positive number of metres", f"pattern.{k}")
    dictionary = pattern.get("dictionary")
    if dictionary is not None:
        dictionary = _dictionary_name(dictionary, where)
    board = Board(kind, grid[0], grid[1], float(numbers[size_key]),
                  float(numbers["marker_size"]) if kind == "charuco" else None, dictionary)
    _check(board, where)
    return board


def to_pattern(board: Board) -> dict:
    if board.kind == "checkerboard":
        return {"type": "checkerboard", "inner_corners": [board.cols, board.rows], "square_size": float(board.size)}
    if board.kind == "charuco":
        d = {"type": "charuco", "squares": [board.cols, board.rows], "square_size": float(board.size),
             "marker_size": float(board.marker)}
        return {**d, "dictionary": board.dictionary} if board.dictionary else d
    return {"type": board.kind, "grid": [board.cols, board.rows], "spacing": float(board.size)}


def points(board: Board) -> np.ndarray:
    """(N, 3) board points in metres, in the order detections index them."""
    s = board.size if board.size is not None else 1.0
    c, r = board.cols, board.rows
    if board.kind == "checkerboard":
        g = np.mgrid[0:c, 0:r].T.reshape(-1, 2) * s
    elif board.kind == "charuco":  # inner chessboard corners, row-major, as cv2.aruco numbers them
        g = (np.mgrid[0:c - 1, 0:r - 1].T.reshape(-1, 2) + 1) * s
    elif board.kind == "circles":
        g = np.mgrid[0:c, 0:r].T.reshape(-1, 2) * s
    else:
        i, j = np.divmod(np.arange(c * r), c)  # row i, column j
        g = np.c_[(2 * j + i % 2) * s, i * s]
    return np.c_[g, np.zeros(len(g))].astype(np.float64)


def _cv_board(board: Board, dictionary: str):
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    return cv2.aruco.CharucoBoard((board.cols, board.rows), board.size, board.marker, d)


_DETECTORS = {}


def _charuco_detector(board: Board):
    if board not in _DETECTORS:
        _DETECTORS[board] = cv2.aruco.CharucoDetector(_cv_board(board, board.dictionary))
    return _DETECTORS[board]


def _candidate_dictionaries(n_markers: int) -> list:
    sized = [f"DICT_{fam}_{next(s for s in ARUCO_SIZES if s >= n_markers)}" for fam in ARUCO_FAMILIES]
    return sized + [d for d in ARUCO_OTHERS if hasattr(cv2.aruco, d)]


def resolve_dictionary(board: Board, grays) -> Board:
    """A ChArUco board with its dictionary named: the one under which most of the board's
    markers are found in the given images (the board unchanged if it names one already)."""
    if board.kind != "charuco" or board.dictionary:
        return board
    n_markers = (board.cols * board.rows) // 2
    best, best_count = None, 0
    for name in _candidate_dictionaries(n_markers):
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        det = cv2.aruco.ArucoDetector(d)
        count = 0
        for gray in grays:
            _, ids, _ = det.detectMarkers(gray)
            count += 0 if ids is None else int(np.sum(ids.ravel() < n_markers))
        if count > best_count:
            best, best_count = name, count
    if best is None:
        raise InputError("--board", f"no ArUco marker of any predefined dictionary found for {board.describe()}")
    return replace(board, dictionary=best)


def detect(gray: np.ndarray, board: Board):
    """``(uv (M, 2) float64, ids (M,) int or None)`` of the board in a grey image, or None.

    ``ids`` index :func:`points`; None means all points, in order. A ChArUco board needs its
    dictionary (see :func:`resolve_dictionary`) and at least 6 corners. A board that looks the
    same turned (``turns(board) > 1``) is numbered by :func:`canonical_order`: which way it was
    really seen is for :func:`resolve_turns` to tell, from the robot's motion."""
    if board.kind == "checkerboard":
        ok, c = cv2.findChessboardCornersSB(gray, (board.cols, board.rows),
                                            flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        return (canonical_order(board, c.reshape(-1, 2).astype(np.float64)), None) if ok else None
    if board.kind == "charuco":
        if not board.dictionary:
            raise ValueError("resolve_dictionary() first: the ChArUco board names no dictionary")
        corners, ids, _, _ = _charuco_detector(board).detectBoard(gray)
        if ids is None or len(ids) < MIN_CHARUCO_CORNERS:
            return None
        ids = ids.ravel().astype(int)
        order = np.argsort(ids)
        return corners.reshape(-1, 2)[order].astype(np.float64), ids[order]
    flags = cv2.CALIB_CB_SYMMETRIC_GRID if board.kind == "circles" else cv2.CALIB_CB_ASYMMETRIC_GRID
    ok, c = cv2.findCirclesGrid(gray, (board.cols, board.rows), flags=flags)
    return (canonical_order(board, c.reshape(-1, 2).astype(np.float64)), None) if ok else None


def board_image(board: Board, px_per_m: float, margin_px: int = 40):
    """A printable image of the board (white background) and the 3x3 ``A`` that maps board
    metres ``[X, Y, 1]`` to its pixel coordinates (OpenCV pixel centres)."""
    s = board.size
    if board.kind == "charuco":
        sq = int(round(s * px_per_m))
        w, h = board.cols * sq + 2 * margin_px, board.rows * sq + 2 * margin_px
        img = _cv_board(board, board.dictionary or "DICT_4X4_50").generateImage((w, h), marginSize=margin_px)
        px_per_m = sq / s
        origin = margin_px - 0.5
    elif board.kind == "checkerboard":
        sq = int(round(s * px_per_m))
        w, h = (board.cols + 1) * sq + 2 * margin_px, (board.rows + 1) * sq + 2 * margin_px
        img = np.full((h, w), 255, np.uint8)
        for i in range(board.rows + 1):
            for j in range(board.cols + 1):
                if (i + j) % 2 == 1:  # the origin's square white: the corner OpenCV's detector starts from
                    img[margin_px + i * sq:margin_px + (i + 1) * sq, margin_px + j * sq:margin_px + (j + 1) * sq] = 0
        px_per_m = sq / s
        origin = margin_px + sq - 0.5  # the first inner corner
    else:
        pts = points(board)[:, :2]
        radius = 0.3 * s * px_per_m
        extent = pts.max(0) * px_per_m
        w, h = (int(np.ceil(extent[0] + 2 * (margin_px + radius))), int(np.ceil(extent[1] + 2 * (margin_px + radius))))
        img = np.full((h, w), 255, np.uint8)
        origin = margin_px + radius
        for x, y in pts * px_per_m + origin:
            cv2.circle(img, (int(round(x * 16)), int(round(y * 16))), int(round(radius * 16)), 0, -1, cv2.LINE_AA, 4)
    A = np.array([[px_per_m, 0, origin], [0, px_per_m, origin], [0, 0, 1.0]])
    return img, A


# --- boards that look the same turned about their normal ---------------------------------------
#
# A checkerboard whose square counts are both even or both odd (inner corners c + r even, e.g.
# 8x6), a symmetric circle grid, and an asymmetric one with an even number of rows look the same
# turned by 180° about the board's normal through its centre (a square one by 90° too): the
# detector cannot tell which corner is the origin, and may number the corners from the opposite
# one in some images. The PnP pose of such a detection is then cam_T_board · T (T the turn), and
# the robot's motion is needed to tell: see resolve_turns.


@lru_cache(maxsize=64)
def turns(board: Board) -> int:
    """How many corner orders a detection of ``board`` cannot tell apart: 1 (none), 2 (the board
    looks the same turned by 180°) or 4 (also by 90°: a square grid)."""
    if board.kind == "charuco":
        return 1  # every marker has its own id
    n = 1
    for k in (4, 2):
        if _turn_permutation(board, k) is not None:
            n = k
            break
    if board.kind == "checkerboard":  # the squares' colours must be turned onto themselves too
        squares = (board.cols + 1, board.rows + 1)
        if n == 4 and squares[0] % 2 == 0:
            n = 2  # a 90° turn swaps black and white
        if n >= 2 and sum(squares) % 2 == 1:
            n = 1  # one count even, one odd: a 180° turn swaps black and white
    return n


@lru_cache(maxsize=64)
def _turn_permutation(board: Board, n: int):
    """``perm`` with ``T p[m] = p[perm[m]]`` for T the turn by 360°/n about the board's centre, or
    None when the board's points are not turned onto themselves."""
    board = Board(board.kind, board.cols, board.rows, 1.0)
    pts = points(board)[:, :2]
    centre = pts.mean(0)
    a = 2 * np.pi / n
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    moved = (pts - centre) @ R.T + centre
    d = np.linalg.norm(moved[:, None] - pts[None], axis=2)
    perm = np.argmin(d, axis=1)
    ok = np.all(d[np.arange(len(pts)), perm] < 1e-6) and len(set(perm.tolist())) == len(pts)
    return perm if ok else None


def turn_matrix(board: Board, k: int, n: int) -> np.ndarray:
    """4x4 board_T_board of k turns by 360°/n about the board's normal through its centre."""
    a = 2 * np.pi * k / n
    c = points(board)[:, :2].mean(0) if board.size else np.zeros(2)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = np.r_[c, 0.0] - R @ np.r_[c, 0.0]
    return M


def turn_detection(board: Board, uv: np.ndarray, k: int, n: int) -> np.ndarray:
    """The corners of a detection renumbered as if seen turned by k·360°/n: a detection whose PnP
    pose is cam_T_board becomes one whose pose is cam_T_board · turn_matrix(board, k, n)^-1."""
    k %= n
    if k == 0:
        return uv
    perm = _turn_permutation(board, n)
    for _ in range(k - 1):
        perm = _turn_permutation(board, n)[perm]
    out = np.empty_like(uv)
    out[perm] = uv  # point m was detected where point perm[m] is
    return out


def unturn_pose(board: Board, cam_T_board, k: int, n: int):
    """The PnP pose of a detection numbered k·360°/n turned, as the board was really seen:
    cam_T_board · T^-k (what turn_detection's renumbering gives)."""
    return cam_T_board if k % n == 0 else cam_T_board.compose(gtsam.Pose3(turn_matrix(board, k, n)).inverse())


def canonical_order(board: Board, uv: np.ndarray) -> np.ndarray:
    """A detection of a board that looks the same turned (turns(board) > 1) renumbered so that
    its first corner is the one nearest the image's top-left (the smallest u + v): the same
    rule whatever order OpenCV's detector happened to return. Which way the board was really
    seen is only told by the robot's motion (resolve_turns)."""
    n = turns(board)
    if n == 1:
        return uv
    cands = [turn_detection(board, uv, k, n) for k in range(n)]
    return min(cands, key=lambda c: (c[0, 0] + c[0, 1], c[0, 1]))


# The robot's nominal flange noise (solver.graph.NoiseOptions' defaults: 0.02°, 0.2 mm), here
# because io does not import the solver; each pair of poses carries it twice.
ROBOT_SIGMA_RAD, ROBOT_SIGMA_M = np.radians(0.02), 0.2e-3
# A pair's evidence is capped at TRUNCATE (5 sigma squared) per invariant, so that one wrong pair
# (a mispaired image, a pose off by degrees) cannot decide a turn; an image's turn is resolved
# when the other turns cost it at least that much more, i.e. one pair's full 5-sigma worth.
TRUNCATE = 25.0


@dataclass
class Turns:
    turns: dict  # frame -> k: the detection was numbered k·360°/n turned; turn_detection(.., k, n) undoes it
    n: int  # turns(board)
    margin: dict  # frame -> how much worse (truncated chi²) the next-best turn of that image fits
    unresolved: list  # frames whose turn the motion cannot tell (margin < TRUNCATE)

    @property
    def turned(self) -> list:
        return sorted(f for f, k in self.turns.items() if k)


def pose_covariances(board: Board, detections: dict, cam_T_board: dict, K, dist) -> dict:
    """{frame: 6x6 PnP covariance of cam_T_board} (pnp_covariance) of ``{frame: (uv, ids)}`` at the
    corners' noise per image coordinate: the pooled reprojection residual of all the poses over
    their redundancy (2 per corner less 6 per pose). (OpenCV's calibration RMS is per corner, both
    coordinates: sqrt(2) times that.)"""
    used = {f: d for f, d in detections.items() if f in cam_T_board}
    dist = np.asarray(dist, float)
    sq, dof = 0.0, 0
    for f, (uv, ids) in used.items():
        M = cam_T_board[f].matrix()
        obj = points(board) if ids is None else points(board)[ids]
        proj, _ = cv2.projectPoints(obj, cv2.Rodrigues(M[:3, :3])[0], M[:3, 3], K, dist)
        sq += float(np.sum((proj.reshape(-1, 2) - uv) ** 2))
        dof += 2 * len(uv) - 6
    sigma = float(np.sqrt(sq / max(dof, 1)))
    return {f: pnp_covariance(board, uv, ids, cam_T_board[f], K, dist, sigma) for f, (uv, ids) in used.items()}


def pnp_covariance(board: Board, uv, ids, cam_T_board, K, dist, sigma_px: float) -> np.ndarray:
    """6x6 covariance of a PnP pose's body tangent ([rot rad, trans m] of cam_T_board · Exp(xi),
    GTSAM's convention) from corners of ``sigma_px`` noise: sigma² (J^T J)^-1, J the Jacobian of
    the projected board points (numerical, central differences)."""
    obj = points(board) if ids is None else points(board)[ids]
    dist = np.asarray(dist, float)

    def project(xi):
        M = cam_T_board.compose(gtsam.Pose3.Expmap(xi)).matrix()
        uv_, _ = cv2.projectPoints(obj, cv2.Rodrigues(M[:3, :3])[0], M[:3, 3], K, dist)
        return uv_.reshape(-1)
    h = 1e-6
    J = np.stack([(project(h * e) - project(-h * e)) / (2 * h) for e in np.eye(6)], 1)
    return sigma_px ** 2 * np.linalg.inv(J.T @ J)


def _angles(Ra, Rb):
    """(N, N) rotation angles (rad) of Ra[i]^T Rb[j]."""
    return np.arccos(np.clip((np.einsum("iab,jab->ij", Ra, Rb) - 1) / 2, -1, 1))


def _pitch(M):
    """(…) screw pitch t · u (u the rotation axis) and angle of 4x4 motions (…, 4, 4)."""
    R, t = M[..., :3, :3], M[..., :3, 3]
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = np.linalg.norm(w, axis=-1)
    return np.einsum("...i,...i->...", w, t) / np.maximum(s, 1e-12), s / 2  # sin(angle)


def resolve_turns(board: Board, cam_T_board: dict, base_T_ee: dict, covariances: dict | None = None) -> Turns:
    """Which way each detection of a board that looks the same turned was numbered, from the robot's motion.

    For a pair of images (i, j) the robot's motion A_ij = base_T_ee_i^-1 base_T_ee_j and the
    camera's B_ij = cam_T_board_i cam_T_board_j^-1 are conjugate (A X = X B), so their rotation
    angles are equal, and so are their screw pitches (translation along the axis, metres) —
    without knowing X. A detection numbered k turns from the truth has cam_T_board · T^k, so
    under the hypothesis that images i and j differ by d turns, B_ij(d) = P_i T^-d P_j^-1. Each
    pair scores every d by the squared, noise-normalised differences of the two invariants
    (truncated at TRUNCATE each); the turns are the labelling that minimises the total, found
    by the spectral synchronisation over the n-th roots of unity (the leading eigenvector of the
    pairs' best d), then refined image by image. The turn most images share is taken as 0 (a
    turn of every image only moves the board's frame). ``covariances``: {frame: 6x6 of
    cam_T_board's body tangent, [rot, trans]} (pnp_covariance); the angle's noise is its
    rotation sigma, the pitch's its translation sigma, with the robot's nominal noise added.
    ``base_T_ee`` in metres (the pitch needs the unit).
    """
    n = turns(board)
    frames = sorted(f for f in cam_T_board if f in base_T_ee)
    N = len(frames)
    if n == 1 or N < 2:
        return Turns({f: 0 for f in frames}, n, {f: np.inf for f in frames}, [])
    P = np.array([cam_T_board[f].matrix() for f in frames])
    Pinv = np.linalg.inv(P)
    E = np.array([base_T_ee[f].matrix() for f in frames])
    if covariances:
        rot_var = np.array([np.trace(covariances[f][:3, :3]) / 3 for f in frames])
        tr_var = np.array([np.trace(covariances[f][3:, 3:]) / 3 for f in frames])
    else:  # a board seen by a usual camera: 0.1° and 1 mm per view
        rot_var, tr_var = np.full(N, np.radians(0.1) ** 2), np.full(N, 1e-3 ** 2)
    sig_ang = np.sqrt(rot_var[:, None] + rot_var[None] + 2 * ROBOT_SIGMA_RAD ** 2)
    sig_t = np.sqrt(tr_var[:, None] + tr_var[None] + 2 * ROBOT_SIGMA_M ** 2)
    ang_A = _angles(E[:, :3, :3], E[:, :3, :3])
    A = np.einsum("iab,jbc->ijac", np.linalg.inv(E), E)
    pitch_A, sin_A = _pitch(A)
    ang_err, pitch_err = np.empty((n, N, N)), np.empty((n, N, N))
    for d in range(n):
        Td = np.linalg.inv(turn_matrix(board, d, n))
        B = np.einsum("iab,bc,jcd->ijad", P, Td, Pinv)
        ang_B = np.arccos(np.clip((np.einsum("ijaa->ij", B[..., :3, :3]) - 1) / 2, -1, 1))
        ang_err[d] = (ang_A - ang_B) / sig_ang
        pitch_B, sin_B = _pitch(B)
        # the axis, hence the pitch, is defined where the rotation is neither ~0 nor ~180°;
        # its noise grows with the lever |t| sigma_angle / sin(angle)
        sin = np.minimum(sin_A, sin_B)
        lever = np.linalg.norm(B[..., :3, 3], axis=-1) * sig_ang / np.maximum(sin, 1e-9)
        pitch_err[d] = np.where(sin > np.sin(np.radians(10)), (pitch_A - pitch_B) / np.hypot(sig_t, lever), np.nan)
    off = ~np.eye(N, dtype=bool)
    cost = np.zeros((n, N, N))
    for err in (ang_err, pitch_err):
        # The robot's real errors are often larger than its nominal noise: the noise scale is the
        # robust spread (MAD) of each pair's best hypothesis, never below the prediction.
        best = np.where(np.isfinite(err), np.abs(err), np.inf).min(0)[off]
        best = best[np.isfinite(best)]
        scale = max(1.0, float(np.median(best)) / 0.6745) if best.size else 1.0
        cost += np.where(np.isfinite(err), np.minimum((err / scale) ** 2, TRUNCATE), 0.0)
    cost[:, ~off] = 0.0
    # spectral synchronisation: H_ij = w_ij omega^(d*_ij), d*_ij = g_i - g_j
    best = np.argmin(cost, axis=0)
    srt = np.sort(cost, axis=0)
    w = srt[1] - srt[0]
    H = w * np.exp(2j * np.pi * best / n)
    H = (H + H.conj().T) / 2
    _, vecs = np.linalg.eigh(H)
    g = np.round(np.angle(vecs[:, -1]) / (2 * np.pi / n)).astype(int) % n

    def frame_costs(g):
        # C[i, k]: image i's total cost with its turn set to k, the others' as in g
        d = (np.arange(n)[:, None, None] - g[None, None, :]) % n  # (n, 1, N): k - g_j
        return np.stack([cost[d[k, 0], np.arange(N)[:, None], np.arange(N)[None]].sum(1)
                         for k in range(n)], 1)  # cost[d, i, j] with d = k - g_j
    for _ in range(2 * N):
        C = frame_costs(g)
        i = int(np.argmax(C[np.arange(N), g] - C.min(1)))
        if C[i, g[i]] - C[i].min() <= 1e-9:
            break
        g[i] = int(np.argmin(C[i]))
    g = (g - np.bincount(g, minlength=n).argmax()) % n
    C = frame_costs(g)
    others = np.where(np.arange(n)[None] == g[:, None], np.inf, C)
    margin = others.min(1) - C[np.arange(N), g]
    # Images can also be tied to each other only by pairs that cannot tell the turns apart (a
    # rotation about the board's normal by 90°, whichever way): then a whole group of them may be
    # turned. Only the images linked to the largest group by pairs that tell (the two best turns
    # 3 sigma apart) are resolved.
    from scipy.sparse.csgraph import connected_components

    _, label = connected_components(w >= 9.0, directed=False)
    margin[label != np.bincount(label).argmax()] = 0.0
    return Turns({f: int(k) for f, k in zip(frames, g)}, n, {f: float(m) for f, m in zip(frames, margin)},
                 [f for f, m in zip(frames, margin) if m < TRUNCATE])


def unresolved_message(board: Board, turned: Turns) -> str:
    """What to tell the user about images whose turn the robot's motion cannot tell (one line)."""
    few = ", ".join(turned.unresolved[:5]) + (f" and {len(turned.unresolved) - 5} more" if len(turned.unresolved) > 5
                                               else "")
    return (f"the {board.describe()} looks the same turned by {360 // turned.n} deg, and the robot's motion cannot "
            f"tell which way it was seen in image(s) {few}: use a ChArUco board (or a checkerboard with one even and "
            "one odd count of squares, e.g. 9x6 inner corners)")


def unturn_detections(board: Board, detections: list, base_T_ee: dict, K, dist, where="--board") -> list:
    """Detections (objects with ``frame``, ``uv``, ``cam_T_board``, ``ids``, e.g. evaluation.pattern's)
    of a board that looks the same turned, renumbered as the robot's motion says the board was seen
    (resolve_turns; ``base_T_ee`` in metres), their poses turned to match; unchanged for other boards.
    Raises InputError naming ``where`` when some image's turn cannot be told."""
    n = turns(board)
    dets = [d for d in detections if d.frame in base_T_ee]
    if n == 1 or len(dets) < 2:
        return detections
    P = {d.frame: d.cam_T_board for d in dets}
    turned = resolve_turns(board, P, base_T_ee, pose_covariances(board, {d.frame: (d.uv, d.ids) for d in dets}, P,
                                                                 K, dist))
    if turned.unresolved:
        raise InputError(where, unresolved_message(board, turned))
    return [replace(d, uv=turn_detection(board, d.uv, k, n), cam_T_board=unturn_pose(board, d.cam_T_board, k, n))
            if (k := turned.turns.get(d.frame, 0)) else d for d in detections]
