"""Reprojection of a calibration pattern's known corners (for the pattern-based reference).

With the board pose ``base_T_board`` and a view's pose ``base_T_cam``, every corner
``P_k`` (board frame, metres) is moved into the camera and projected with OpenCV's
camera model (the dataset's OPENCV: radial k1, k2 and tangential p1, p2; FULL_OPENCV adds
k3 and the rational k4, k5, k6) onto the detected, *raw* (distorted) pixel ``u_k``:

    Q_k = cam_T_board * (b * P_k),     x, y = Q_x / Q_z, Q_y / Q_z,     r2 = x^2 + y^2
    c   = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)   (k3-k6 = 0 for OPENCV)
    x_d = x c + 2 p1 x y + p2 (r2 + 2 x^2)
    y_d = y c + p1 (r2 + 2 y^2) + 2 p2 x y
    r_k = (fx x_d + cx - u_k, fy y_d + cy - v_k) / sigma_px       (2 rows per corner)

Keys: ``[base_T_board (Pose3), base_T_cam (Pose3)]``; optionally the camera's intrinsics
``[fx, fy, cx, cy, k1, k2, p1, p2]`` (Vector 8, OPENCV) or ``[.., k3, k4, k5, k6]`` (Vector 12,
FULL_OPENCV), which then replace the measurement's
fixed ones; and optionally (when the measurement says ``board_scale``) the board's scale
``b`` (double, last key; otherwise b = 1). A printed board is often 0.1-0.5 % off its
nominal square size, and with a camera 1 m from the board that biases a pattern hand-eye
by 1-5 mm along the optical axis; the robot's metric motion makes ``b`` observable.

Refining the focal length and principal point on corners undistorted with the *old*
intrinsics is not one camera model (OpenCV's distortion acts on normalised coordinates,
which move with K): the adjusted camera is therefore projected in full, on raw corners.
Error dimension 2N, in units of sigma_px.
"""

from dataclasses import dataclass
from functools import partial

import gtsam
import numpy as np

from factors.reprojection import transform_one_way


@dataclass(frozen=True)
class PatternMeasurement:
    corners_board: np.ndarray  # (N, 3) corner positions in the board frame, metres
    uv: np.ndarray  # (N, 2) detected (distorted) pixels
    intrinsics: np.ndarray  # (8,) or (12,): fx, fy, cx, cy, k1, k2, p1, p2[, k3, k4, k5, k6] when no intrinsics key
    sigma_px: float = 0.5
    board_scale: bool = False  # the last key is the board's scale factor


def distort(x, y, dist):
    """OpenCV's lens model on normalised coordinates (N,), ``dist`` = [k1, k2, p1, p2] or [k1, k2, p1,
    p2, k3, k4, k5, k6]: ``(x_d, y_d)`` and the Jacobians ``d(x_d, y_d)/d(x, y)`` (N, 2, 2) and
    ``d(x_d, y_d)/d dist`` (N, 2, len(dist))."""
    k1, k2, p1, p2, k3, k4, k5, k6 = np.r_[dist, np.zeros(8 - len(dist))]
    r2 = x * x + y * y
    num, den = 1 + r2 * (k1 + r2 * (k2 + r2 * k3)), 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    d_num, d_den = k1 + r2 * (2 * k2 + 3 * k3 * r2), k4 + r2 * (2 * k5 + 3 * k6 * r2)  # d / d r2
    d_radial = 2 * (d_num * den - num * d_den) / den ** 2  # d radial / d r2, times 2 for d r2 / dx = 2x
    J_xy = np.empty((len(x), 2, 2))
    J_xy[:, 0, 0] = radial + x * x * d_radial + 2 * p1 * y + 6 * p2 * x
    J_xy[:, 0, 1] = x * y * d_radial + 2 * p1 * x + 2 * p2 * y
    J_xy[:, 1, 0] = x * y * d_radial + 2 * p1 * x + 2 * p2 * y
    J_xy[:, 1, 1] = radial + y * y * d_radial + 6 * p1 * y + 2 * p2 * x
    r4, r6 = r2 * r2, r2 * r2 * r2
    # d radial / d (k1, k2, k3, k4, k5, k6)
    d_k = np.stack([r2 / den, r4 / den, r6 / den, -radial * r2 / den, -radial * r4 / den, -radial * r6 / den], 1)
    J_dist = np.empty((len(x), 2, 8))
    J_dist[:, 0, [0, 1, 4, 5, 6, 7]] = x[:, None] * d_k
    J_dist[:, 1, [0, 1, 4, 5, 6, 7]] = y[:, None] * d_k
    J_dist[:, 0, 2:4] = np.stack([2 * x * y, r2 + 2 * x * x], axis=1)
    J_dist[:, 1, 2:4] = np.stack([r2 + 2 * y * y, 2 * x * y], axis=1)
    return xd, yd, J_xy, J_dist[:, :, :len(dist)]


def pattern_error(m: PatternMeasurement, this, values, jacobians):
    keys = this.keys()
    board_T_cam = values.atPose3(keys[0]).between(values.atPose3(keys[1]))
    with_intrinsics = len(keys) - int(m.board_scale) == 3
    k = values.atVector(keys[2]) if with_intrinsics else m.intrinsics
    fx, fy, cx, cy = k[:4]
    scale = values.atDouble(keys[-1]) if m.board_scale else 1.0
    Q, dQ = transform_one_way(m.corners_board, board_T_cam, scale)
    z = Q[:, 2]
    x, y = Q[:, 0] / z, Q[:, 1] / z
    xd, yd, J_xy, J_dist = distort(x, y, k[4:])
    r = np.stack([fx * xd + cx - m.uv[:, 0], fy * yd + cy - m.uv[:, 1]], axis=1) / m.sigma_px
    if jacobians is not None:
        n = len(Q)
        d_xy = np.zeros((n, 2, 3))  # d(x, y)/dQ
        d_xy[:, 0, 0], d_xy[:, 0, 2] = 1 / z, -x / z
        d_xy[:, 1, 1], d_xy[:, 1, 2] = 1 / z, -y / z
        d_uv = np.array([fx, fy])[None, :, None] * (J_xy @ d_xy) / m.sigma_px  # d r / dQ
        jacobians[0] = (d_uv @ dQ[0]).reshape(-1, 6)
        jacobians[1] = (d_uv @ dQ[1]).reshape(-1, 6)
        if m.board_scale:
            jacobians[len(keys) - 1] = (d_uv @ dQ[2]).reshape(-1, 1)
        if with_intrinsics:
            Jk = np.zeros((n, 2, len(k)))
            Jk[:, 0, 0], Jk[:, 0, 2] = xd, 1.0
            Jk[:, 1, 1], Jk[:, 1, 3] = yd, 1.0
            Jk[:, :, 4:] = np.array([fx, fy])[None, :, None] * J_dist
            jacobians[2] = Jk.reshape(-1, len(k)) / m.sigma_px
    return r.reshape(-1)


def make_pattern_factor(m: PatternMeasurement, keys) -> gtsam.CustomFactor:
    """One factor per view over all its corners (whitened by sigma_px)."""
    noise = gtsam.noiseModel.Unit.Create(2 * len(m.uv))
    return gtsam.CustomFactor(noise, list(keys), partial(pattern_error, m))
