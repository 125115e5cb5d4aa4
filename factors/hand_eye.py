"""Hand-eye factors: the camera trajectory against the robot's measured flange poses.

**Robot pose factor** (absolute form of AX = XB, used by the solver). For frame t
with measured ``base_T_ee(t)`` and the view of camera j at that frame:

    e = Log( (base_T_ee(t) * ee_T_cam_j)^-1 * base_T_cam(t) )          (6,: rad, m)

For any two frames t1, t2 it implies A X = X B with A = ee(t1)_T_ee(t2) and
B = cam(t1)_T_cam(t2): the relative-motion equation of the paper. We solve the
absolute form because each robot measurement then enters the graph exactly once
(relative motions share poses and would count their noise twice), and the visual
world is anchored in the robot base frame with metric units, which fixes the
gauge of every connected component without an arbitrary prior. The metric scale
lives in the views' depth scales. Keys: ``[ee_T_cam (Pose3), base_T_cam (Pose3)]``.

**Relative scaled AX = XB** (Calib3R eq. 8), for graphs whose visual world is in
reconstruction units: with A = ee(t1)_T_ee(t2) from the robot, visual poses
``world_T_cam`` in reconstruction units and metric scale lambda,

    B_lambda = (R_B, lambda * t_B),     e = Log( (A X)^-1 * X * B_lambda )     (6,)

Keys: ``[ee_T_cam, world_T_cam(t1), world_T_cam(t2), lambda (double)]``.
Noise models (propagated from the robot's pose noise) are built by the caller.
"""

from functools import partial

import gtsam
import numpy as np

from factors._lie import log_with_jacobian


def robot_pose_error(base_T_ee: gtsam.Pose3, this: gtsam.CustomFactor, values: gtsam.Values,
                     jacobians) -> np.ndarray:
    k_x, k_c = this.keys()
    ee_T_cam, base_T_cam = values.atPose3(k_x), values.atPose3(k_c)
    D = base_T_ee.compose(ee_T_cam).between(base_T_cam)  # X^-1 E^-1 C
    e, Jlog = log_with_jacobian(D)
    if jacobians is not None:
        # X -> X Exp(xi): D -> Exp(-xi) D = D Exp(-Ad(D^-1) xi);  C -> C Exp(xi): D -> D Exp(xi)
        jacobians[0] = -Jlog @ D.inverse().AdjointMap()
        jacobians[1] = Jlog
    return e


def make_robot_pose_factor(base_T_ee: gtsam.Pose3, keys, noise) -> gtsam.CustomFactor:
    return gtsam.CustomFactor(noise, list(keys), partial(robot_pose_error, base_T_ee))


def robot_pose_noise_covariance(ee_T_cam: gtsam.Pose3, sigma_rot_rad: float, sigma_trans_m: float) -> np.ndarray:
    """6x6 covariance of the robot pose factor's error from isotropic flange-pose noise.

    A flange perturbation ``base_T_ee * Exp(delta)`` moves the error by
    ``-Ad(ee_T_cam^-1) delta`` (at the solution), so the covariance is
    ``Ad Sigma_delta Ad^T``.
    """
    Sigma = np.diag([sigma_rot_rad**2] * 3 + [sigma_trans_m**2] * 3)
    Ad = ee_T_cam.inverse().AdjointMap()
    return Ad @ Sigma @ Ad.T


def _scaled(pose: gtsam.Pose3, scale: float) -> gtsam.Pose3:
    return gtsam.Pose3(pose.rotation(), scale * pose.translation())


def relative_hand_eye_error(ee1_T_ee2: gtsam.Pose3, this: gtsam.CustomFactor, values: gtsam.Values,
                            jacobians) -> np.ndarray:
    k_x, k_c1, k_c2, k_l = this.keys()
    X = values.atPose3(k_x)
    C1, C2 = values.atPose3(k_c1), values.atPose3(k_c2)
    lam = values.atDouble(k_l)
    B = C1.between(C2)
    B_l = _scaled(B, lam)
    AX = ee1_T_ee2.compose(X)
    XB = X.compose(B_l)
    D = AX.between(XB)  # (A X)^-1 X B_lambda
    e, Jlog = log_with_jacobian(D)
    if jacobians is not None:
        # X appears twice: D = X^-1 A^-1 X B_l.
        #   left X^-1:  D -> Exp(-xi) D            = D Exp(-Ad(D^-1) xi)
        #   right X:    X B_l -> X Exp(xi) B_l     = X B_l Exp(Ad(B_l^-1) xi)
        H_x = -D.inverse().AdjointMap() + B_l.inverse().AdjointMap()
        # B_lambda from B: right perturbation [w, v] of B maps to [w, lambda v] of B_lambda;
        # lambda -> lambda + dl moves B_lambda by [0, R_B^T t_B dl].
        S = np.diag([1.0, 1, 1, lam, lam, lam])
        # B = C1^-1 C2: C1 -> C1 Exp(xi) gives B Exp(-Ad(B^-1) xi); C2 -> C2 Exp(xi) gives B Exp(xi)
        H_c1 = S @ (-B.inverse().AdjointMap())
        H_c2 = S
        H_l = np.concatenate([np.zeros(3), B.rotation().matrix().T @ B.translation()])[:, None]
        jacobians[0] = Jlog @ H_x
        jacobians[1] = Jlog @ H_c1
        jacobians[2] = Jlog @ H_c2
        jacobians[3] = Jlog @ H_l
    return e


def make_relative_hand_eye_factor(ee1_T_ee2: gtsam.Pose3, keys, noise) -> gtsam.CustomFactor:
    return gtsam.CustomFactor(noise, list(keys), partial(relative_hand_eye_error, ee1_T_ee2))
