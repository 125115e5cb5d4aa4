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
    really seen is for ``board_turns.resolve_turns`` to tell, from the robot's motion."""
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
# the robot's motion is needed to tell: see calib3r_graph/io/board_turns.py. What detect needs to
# number such a board the same way in every image (canonical_order) stays here.


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


def turn_detection(board: Board, uv: np.ndarray, k: int, n: int) -> np.ndarray:
    """The corners of a detection renumbered as if seen turned by k·360°/n: a detection whose PnP
    pose is cam_T_board becomes one whose pose is cam_T_board · board_turns.turn_matrix(board, k, n)^-1."""
    k %= n
    if k == 0:
        return uv
    perm = _turn_permutation(board, n)
    for _ in range(k - 1):
        perm = _turn_permutation(board, n)[perm]
    out = np.empty_like(uv)
    out[perm] = uv  # point m was detected where point perm[m] is
    return out


def canonical_order(board: Board, uv: np.ndarray) -> np.ndarray:
    """A detection of a board that looks the same turned (turns(board) > 1) renumbered so that
    its first corner is the one nearest the image's top-left (the smallest u + v): the same
    rule whatever order OpenCV's detector happened to return. Which way the board was really
    seen is only told by the robot's motion (board_turns.resolve_turns)."""
    n = turns(board)
    if n == 1:
        return uv
    cands = [turn_detection(board, uv, k, n) for k in range(n)]
    return min(cands, key=lambda c: (c[0, 0] + c[0, 1], c[0, 1]))
