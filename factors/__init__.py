"""GTSAM factor library of calib3r-graph: one module per constraint family.

Every factor is a pure error function ``f(measurement, this, values, jacobians)``
bound with :func:`functools.partial` into a :class:`gtsam.CustomFactor`; noise
models are chosen by the caller (graph assembly), never inside the factor.

Frame and perturbation rules, stated once for the whole library:

* ``a_T_b`` maps points in frame b to frame a: ``p_a = a_T_b * p_b``.
* Poses are :class:`gtsam.Pose3` with GTSAM's right perturbation
  ``T = T_hat * Exp([w; v])``, tangent order ``[wx, wy, wz, vx, vy, vz]``
  (radians, metres), ``v`` in the body frame.
* Scalars (depth scales, metric scales) are plain Python floats in ``gtsam.Values``.
"""

from factors.hand_eye import make_robot_pose_factor, robot_pose_error, relative_hand_eye_error, make_relative_hand_eye_factor
from factors.match3d import Match3DMeasurement, make_match3d_factor, match3d_error
from factors.reprojection import ReprojectionMeasurement, make_reprojection_factor, reprojection_error
from factors.rigidity import make_rigidity_factor, rigidity_error
from factors.scale_gauge import make_scale_gauge_factor, scale_gauge_error

__all__ = [
    "Match3DMeasurement", "match3d_error", "make_match3d_factor",
    "ReprojectionMeasurement", "reprojection_error", "make_reprojection_factor",
    "robot_pose_error", "make_robot_pose_factor",
    "relative_hand_eye_error", "make_relative_hand_eye_factor",
    "rigidity_error", "make_rigidity_factor",
    "scale_gauge_error", "make_scale_gauge_factor",
]
