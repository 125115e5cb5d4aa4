"""Boards that look the same turned about their normal: which way each image really saw them.

A checkerboard whose square counts are both even or both odd (e.g. 8x6 inner corners), a
symmetric circle grid, and an asymmetric one with an even number of rows look the same turned
by 180° about the board's normal through its centre (a square grid by 90° too): a *turn*. The
detector cannot tell which corner is the origin, so :func:`calib3r_graph.io.boards.detect`
numbers such a board by one fixed rule (``boards.canonical_order``), and in some images that
numbering starts from the opposite corner: the PnP pose is then cam_T_board · T (T the turn).

The robot's motion tells which: a flange motion and the camera's motion between two images are
conjugate (AX = XB), so their rotation angles and screw pitches agree without knowing X, for the
right turns only. :func:`resolve_turns` scores every pair of images under each relative turn,
finds the labelling that agrees best with all of them (spectral synchronisation, then refined
image by image) and names the images it cannot tell; :func:`unturn_detections` renumbers the
detections and turns their poses to match.
"""

from dataclasses import dataclass, replace

import cv2
import gtsam
import numpy as np

from calib3r_graph.errors import InputError
from calib3r_graph.io.boards import Board, points, turn_detection, turns


def turn_matrix(board: Board, k: int, n: int) -> np.ndarray:
    """4x4 board_T_board of k turns by 360°/n about the board's normal through its centre."""
    a = 2 * np.pi * k / n
    c = points(board)[:, :2].mean(0) if board.size else np.zeros(2)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = np.r_[c, 0.0] - R @ np.r_[c, 0.0]
    return M


def unturn_pose(board: Board, cam_T_board, k: int, n: int):
    """The PnP pose of a detection numbered k·360°/n turned, as the board was really seen:
    cam_T_board · T^-k (what turn_detection's renumbering gives)."""
    return cam_T_board if k % n == 0 else cam_T_board.compose(gtsam.Pose3(turn_matrix(board, k, n)).inverse())


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
