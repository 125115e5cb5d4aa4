"""Reprojection of a calibration pattern's known corners (for the pattern-based reference).

With the board pose ``base_T_board`` and a view's pose ``base_T_cam``, every corner
``P_k`` (board frame, metres) projects to

    r_k = W (pi(K, cam_T_board * P_k) - u_k)                    (2 rows per corner, whitened)

Keys: ``[base_T_board (Pose3), base_T_cam (Pose3)]``, optionally the camera's intrinsics
``k = [fx, fy, cx, cy]`` (Vector 4), which then replace ``K``, and optionally (when the
measurement says ``board_scale``) the board's scale ``b`` (double, last key): the corners are
then ``b * P_k``. A printed board is often 0.1-0.5 % off its nominal square size, and with a
camera 1 m from the board that biases a pattern hand-eye by 1-5 mm along the optical axis;
the robot's metric motion makes ``b`` observable. Error dimension 2N.
"""

from dataclasses import dataclass
from functools import partial

import gtsam
import numpy as np

from factors.reprojection import _project_one_way


@dataclass(frozen=True)
class PatternMeasurement:
    corners_board: np.ndarray  # (N, 3) corner positions in the board frame
    uv: np.ndarray  # (N, 2) detected pixels
    K: np.ndarray  # (3, 3)
    sigma_px: float = 0.5
    board_scale: bool = False  # the last key is the board's scale factor


def pattern_error(m: PatternMeasurement, this, values, jacobians):
    keys = this.keys()
    board_T_cam = values.atPose3(keys[0]).between(values.atPose3(keys[1]))
    K = m.K
    with_intrinsics = len(keys) - int(m.board_scale) == 3
    if with_intrinsics:
        fx, fy, cx, cy = values.atVector(keys[2])
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    scale = values.atDouble(keys[-1]) if m.board_scale else 1.0
    r, J = _project_one_way(m.corners_board, m.uv, K, board_T_cam, scale)
    if jacobians is not None:
        jacobians[0] = J[0].reshape(-1, 6) / m.sigma_px
        jacobians[1] = J[1].reshape(-1, 6) / m.sigma_px
        if m.board_scale:
            jacobians[len(keys) - 1] = J[2].reshape(-1, 1) / m.sigma_px
        if with_intrinsics:
            # u = fx x/z + cx, v = fy y/z + cy  ->  normalised coordinates from the residual
            xn = (r[:, 0] + m.uv[:, 0] - K[0, 2]) / K[0, 0]
            yn = (r[:, 1] + m.uv[:, 1] - K[1, 2]) / K[1, 1]
            Jk = np.zeros((len(r), 2, 4))
            Jk[:, 0, 0], Jk[:, 0, 2] = xn, 1.0
            Jk[:, 1, 1], Jk[:, 1, 3] = yn, 1.0
            jacobians[2] = Jk.reshape(-1, 4) / m.sigma_px
    return r.reshape(-1) / m.sigma_px


def make_pattern_factor(m: PatternMeasurement, keys) -> gtsam.CustomFactor:
    """One factor per view over all its corners (whitened by sigma_px)."""
    noise = gtsam.noiseModel.Unit.Create(2 * len(m.uv))
    return gtsam.CustomFactor(noise, list(keys), partial(pattern_error, m))
