"""Cross-camera rigidity of a multi-camera rig (Calib3R eq. 10).

At frame t the views of the reference camera r and of camera j are related by
the fixed mount: ``cam_r_T_cam_j = ee_T_cam_r^-1 * ee_T_cam_j``. The residual
compares that with the two views' poses:

    e = Log( (ee_T_cam_r^-1 ee_T_cam_j)^-1 * base_T_cam_r(t)^-1 base_T_cam_j(t) )   (6,: rad, m)

With it, each robot measurement enters the graph once (through the reference
camera's robot pose factor) however many cameras the rig has.
Keys: ``[ee_T_cam_r, ee_T_cam_j, base_T_cam_r(t), base_T_cam_j(t)]`` (all Pose3).
"""

from functools import partial

import gtsam
import numpy as np

from factors._lie import log_with_jacobian


def rigidity_error(_unused, this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
    k_xr, k_xj, k_cr, k_cj = this.keys()
    X_r, X_j = values.atPose3(k_xr), values.atPose3(k_xj)
    C_r, C_j = values.atPose3(k_cr), values.atPose3(k_cj)
    N = C_r.between(C_j)
    M = X_r.between(X_j).between(N)  # X_j^-1 X_r C_r^-1 C_j
    e, Jlog = log_with_jacobian(M)
    if jacobians is not None:
        Ad_Ninv = N.inverse().AdjointMap()
        jacobians[0] = Jlog @ Ad_Ninv  # X_r Exp(xi): M Exp(Ad(N^-1) xi)
        jacobians[1] = -Jlog @ M.inverse().AdjointMap()  # X_j Exp(xi): Exp(-xi) M
        jacobians[2] = -Jlog @ Ad_Ninv  # C_r Exp(xi): M Exp(-Ad(N^-1) xi)
        jacobians[3] = Jlog  # C_j Exp(xi): M Exp(xi)
    return e


def make_rigidity_factor(keys, noise) -> gtsam.CustomFactor:
    return gtsam.CustomFactor(noise, list(keys), partial(rigidity_error, None))
