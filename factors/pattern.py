"""Reprojection of a calibration pattern's known corners (for the pattern-based reference).

With the board pose ``base_T_board`` and a view's pose ``base_T_cam``, every corner
``P_k`` (board frame, metres) projects to

    r_k = W (pi(K, cam_T_board * P_k) - u_k)                    (2 rows per corner, whitened)

Keys: ``[base_T_board (Pose3), base_T_cam (Pose3)]``. Error dimension 2N.
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


def pattern_error(m: PatternMeasurement, this, values, jacobians):
    k_board, k_cam = this.keys()
    board_T_cam = values.atPose3(k_board).between(values.atPose3(k_cam))
    r, J = _project_one_way(m.corners_board, m.uv, m.K, board_T_cam, 1.0)
    if jacobians is not None:
        jacobians[0] = J[0].reshape(-1, 6) / m.sigma_px
        jacobians[1] = J[1].reshape(-1, 6) / m.sigma_px
    return r.reshape(-1) / m.sigma_px


def make_pattern_factor(m: PatternMeasurement, keys) -> gtsam.CustomFactor:
    """One factor per view over all its corners (whitened by sigma_px)."""
    noise = gtsam.noiseModel.Unit.Create(2 * len(m.uv))
    return gtsam.CustomFactor(noise, list(keys), partial(pattern_error, m))
