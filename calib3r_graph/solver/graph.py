"""Assembly of the one joint factor graph.

Variables (GTSAM keys):
    x<i>  base_T_cam of view i (Pose3, metres, robot base frame)
    s<i>  depth scale of view i (double: metres per frontend depth unit)
    c<i>  smooth depth correction of view i (Vector 5, relative; see factors.match3d)
    e<j>  ee_T_cam of camera j (Pose3)
    l<j>  metric scale of camera j (double: geometric mean of its views' depth scales)

Factors: one 3D match factor per view pair (optionally one reprojection factor per
pair), one robot pose factor per frame on its reference view (the first camera with
a view at that frame), one rigidity factor per other view of that frame, and one
scale-gauge factor per camera.

Gauge: the scene factors are invariant to a similarity transform of the visual
world. We fix that freedom on purpose through the robot: every connected component
of the co-visibility graph has views at two or more robot poses (others are left
out by the initialiser), and their robot pose factors tie the component's pose and
scale to the metric robot base frame. No view is anchored by an arbitrary prior, so
the covariance of ee_T_cam does not depend on any choice of anchor view.
"""

from dataclasses import dataclass

import gtsam
import numpy as np

import factors
from factors.hand_eye import robot_pose_noise_covariance
from factors.match3d import DEPTH_CORRECTION_DIM, Match3DMeasurement, match3d_residuals, match3d_whitened
from calib3r_graph.io.predictions import split_view_id


@dataclass
class NoiseOptions:
    pixel_sigma_px: float = 1.0  # match noise on the frontend's grid
    depth_sigma_rel: float = 0.01  # relative depth noise of the frontend
    robot_sigma_mm: float = 0.2  # flange position noise of the robot
    robot_sigma_deg: float = 0.02  # flange orientation noise of the robot
    rig_sigma_mm: float = 0.02  # non-rigidity / desynchronisation between rig cameras
    rig_sigma_deg: float = 0.002
    scale_gauge_sigma: float = 1e-6  # tight: lambda_j is a defined quantity, not a measurement
    depth_correction_sigma: float = 0.02  # prior on each relative depth-correction coefficient (0 = off)


# A view pair makes a 3D match factor with at least this many matches of non-zero weight (fewer
# cannot fix the relative pose and scale it constrains); every place that asks whether a pair is in
# the graph asks this.
MIN_FACTOR_MATCHES = 3


class Keys:
    def __init__(self, views, cameras):
        self.view_index = {v: i for i, v in enumerate(views)}
        self.cameras = list(cameras)

    def pose(self, v):
        return gtsam.symbol("x", self.view_index[v])

    def scale(self, v):
        return gtsam.symbol("s", self.view_index[v])

    def correction(self, v):
        return gtsam.symbol("c", self.view_index[v])

    def hand_eye(self, cam):
        return gtsam.symbol("e", self.cameras.index(cam))

    def metric(self, cam):
        return gtsam.symbol("l", self.cameras.index(cam))

    def describe(self, letter: str, index: int) -> str | None:
        """A GTSAM key of this graph in words that name the view (camera and frame) or the camera,
        e.g. ("s", 6) -> "the depth scale of view cam0/0006 (camera cam0, frame 0006)"; None if unknown."""
        views = list(self.view_index)
        what = {"x": "the pose", "s": "the depth scale", "c": "the depth correction"}.get(letter)
        if what and 0 <= index < len(views):
            cam, frame = split_view_id(views[index])
            return f"{what} of view {views[index]} (camera {cam}, frame {frame})"
        what = {"e": "ee_T_cam", "l": "metric scale (shared by its views' depth scales)"}.get(letter)
        if what and 0 <= index < len(self.cameras):
            return f"camera {self.cameras[index]}'s {what}"
        return None


def point_sqrt_info(obs, K_a, K_b, a_T_b: gtsam.Pose3, scale_ratio_b_to_a: float, noise: NoiseOptions,
                    weights: np.ndarray, covariances=None) -> np.ndarray:
    """(N, 3, 3) square-root information of e_p = P_a - a_T_b P_b (view a's unit depth scale).

    Each point's covariance comes from pixel noise (lateral, sigma_px * depth / f) and
    relative depth noise (along the viewing ray); view b's is rotated into a's frame and
    rescaled to a's units. ``weights`` (confidence x robust weight) scale the information.
    ``covariances``: :func:`point_covariances` of ``obs``, if already computed (they do not depend
    on the views' poses or scales, so a caller that whitens one pair at many points keeps them).
    """
    C_a, C_b = point_covariances(obs, K_a, K_b, noise) if covariances is None else covariances
    R = a_T_b.rotation().matrix()
    # R C_b R^T for every point at once: vec(R C R^T) = (R kron R) vec(C) (4x the batched product)
    RR = (R[:, None, :, None] * R[None, :, None, :]).reshape(9, 9)  # R kron R (np.kron: 0.1 ms a call)
    C = C_a + (C_b.reshape(-1, 9) @ (scale_ratio_b_to_a**2 * RR).T).reshape(-1, 3, 3)
    return inverse_cholesky_3x3(C) * np.sqrt(weights)[:, None, None]


def point_covariances(obs, K_a, K_b, noise: NoiseOptions) -> tuple[np.ndarray, np.ndarray]:
    """Each match's point covariance (N, 3, 3) in its own camera, in that view's frontend-depth unit:
    ``sigma_d^2 P P^T + diag((sigma_px z / fx)^2, (sigma_px z / fy)^2, 0)``, for view a and view b."""
    def cov(pts, K):
        z2 = (noise.pixel_sigma_px * pts[:, 2]) ** 2
        sp = noise.depth_sigma_rel**2 * pts
        C = sp[:, :, None] * pts[:, None, :]
        C[:, 0, 0] += z2 / K[0, 0] ** 2
        C[:, 1, 1] += z2 / K[1, 1] ** 2
        return C

    return cov(obs.pts_a, K_a), cov(obs.pts_b, K_b)


def inverse_cholesky_3x3(C: np.ndarray) -> np.ndarray:
    """W = L^-1 with C = L L^T, for a batch of SPD 3x3 matrices (N, 3, 3): |W e|^2 = e^T C^-1 e.

    Written out in closed form: numpy's batched cholesky + inv cost ~10x more at this size.
    """
    l00 = np.sqrt(C[:, 0, 0])
    l10, l20 = C[:, 1, 0] / l00, C[:, 2, 0] / l00
    l11 = np.sqrt(C[:, 1, 1] - l10**2)
    l21 = (C[:, 2, 1] - l20 * l10) / l11
    l22 = np.sqrt(C[:, 2, 2] - l20**2 - l21**2)
    W = np.zeros_like(C)
    W[:, 0, 0], W[:, 1, 1], W[:, 2, 2] = 1 / l00, 1 / l11, 1 / l22
    W[:, 1, 0] = -l10 / (l00 * l11)
    W[:, 2, 1] = -l21 / (l11 * l22)
    W[:, 2, 0] = -(l20 * W[:, 0, 0] + l21 * W[:, 1, 0]) / l22
    return W


def add_scene_factors(graph, keys, observations, weights, values_init, Ks, noise, reprojection=False,
                      whitening=None):
    """One 3D match factor (and optionally one reprojection factor) per view pair. ``whitening``:
    each pair's :func:`point_sqrt_info` at ``values_init`` with unit weights, if already computed
    (the same numbers: each point's is its own)."""
    for i, (o, w) in enumerate(zip(observations, weights)):
        keep = w > 0
        if keep.sum() < MIN_FACTOR_MATCHES:
            continue
        if not keep.all():  # (a copy of every array otherwise)
            o = o.subset(keep)
        w = w[keep]
        if whitening is not None:
            W = whitening[i][keep] * np.sqrt(w)[:, None, None]
        else:
            T_a, T_b = values_init.atPose3(keys.pose(o.view_a)), values_init.atPose3(keys.pose(o.view_b))
            s_a, s_b = values_init.atDouble(keys.scale(o.view_a)), values_init.atDouble(keys.scale(o.view_b))
            W = point_sqrt_info(o, Ks[o.view_a], Ks[o.view_b], T_a.between(T_b), s_b / s_a, noise, w)
        k = [keys.pose(o.view_a), keys.pose(o.view_b), keys.scale(o.view_a), keys.scale(o.view_b)]
        if noise.depth_correction_sigma > 0:
            m = factors.Match3DMeasurement(o.pts_a, o.pts_b, W, o.basis_a, o.basis_b)
            k3d = k + [keys.correction(o.view_a), keys.correction(o.view_b)]
        else:
            m, k3d = factors.Match3DMeasurement(o.pts_a, o.pts_b, W), k
        graph.add(factors.make_match3d_factor(m, k3d))
        if reprojection:
            W2 = np.eye(2)[None] * (np.sqrt(w) / noise.pixel_sigma_px)[:, None, None]
            basis = (o.basis_a, o.basis_b) if noise.depth_correction_sigma > 0 else (None, None)
            m = factors.ReprojectionMeasurement(o.pts_a, o.pts_b, o.uv_a, o.uv_b, Ks[o.view_a], Ks[o.view_b], W2,
                                                *basis)
            graph.add(factors.make_reprojection_factor(m, k3d))


def scene_keys(o, keys, noise) -> list:
    """The 3D match factor's keys, in its order (add_scene_factors)."""
    k = [keys.pose(o.view_a), keys.pose(o.view_b), keys.scale(o.view_a), keys.scale(o.view_b)]
    return k + ([keys.correction(o.view_a), keys.correction(o.view_b)] if noise.depth_correction_sigma > 0 else [])


def scene_linearisation(o, w, values, keys, Ks, noise, whitening=None):
    """The 3D match factor that :func:`add_scene_factors` makes of pair ``o`` with weights ``w``,
    linearised at ``values`` by hand: (its keys, its observations, their W (n, 3, 3), the
    whitened Jacobian J (3n, D) in the keys' order and tangent spaces, the whitened residual e
    (3n,)), or None where it makes no factor. The matches of zero weight are zero rows of W, J and
    e (the same sums), or, where they are more than half, left out of all four. GTSAM's
    linearisation of that factor is A = J, b = -e (its row compression is exact), so one Jacobian
    can serve both the linear system and what else needs J (solver/camera_model.py).
    ``whitening``: the pair's point_sqrt_info at ``values`` with unit weights, if already computed."""
    keep = w > 0
    n_keep = int(keep.sum())
    if n_keep < MIN_FACTOR_MATCHES:
        return None
    if n_keep < 0.5 * len(o):  # (above, the matches of zero weight stay as zero rows: no copy of the pair)
        o, w, whitening = o.subset(keep), w[keep], None if whitening is None else whitening[keep]
    if whitening is not None:
        W = whitening * np.sqrt(w)[:, None, None]
    else:
        T_a, T_b = values.atPose3(keys.pose(o.view_a)), values.atPose3(keys.pose(o.view_b))
        W = point_sqrt_info(o, Ks[o.view_a], Ks[o.view_b], T_a.between(T_b),
                            values.atDouble(keys.scale(o.view_b)) / values.atDouble(keys.scale(o.view_a)), noise, w)
    k = scene_keys(o, keys, noise)
    basis = (o.basis_a, o.basis_b) if noise.depth_correction_sigma > 0 else (None, None)
    e, J, _ = match3d_whitened(Match3DMeasurement(o.pts_a, o.pts_b, W, *basis), k, values)
    return k, o, W, J, e


def robot_views(keys, views) -> list:
    """The view of each frame that carries its robot pose factor: the first camera's (a rig's other
    cameras are tied to it by rigidity)."""
    by_frame = {}
    for v in views:
        by_frame.setdefault(split_view_id(v)[1], []).append(v)
    return [min(vs, key=lambda v: keys.cameras.index(split_view_id(v)[0])) for vs in by_frame.values()]


def add_robot_factors(graph, keys, views, base_T_ee, ee_T_cam_init, noise: NoiseOptions):
    """Robot pose factor on each frame's reference view; rigidity for the frame's other views."""
    by_frame = {}
    for v in views:
        cam, frame = split_view_id(v)
        by_frame.setdefault(frame, []).append(v)
    rig_noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[[np.radians(noise.rig_sigma_deg)] * 3,
                                                       [noise.rig_sigma_mm * 1e-3] * 3])
    for frame, vs in by_frame.items():
        vs = sorted(vs, key=lambda v: keys.cameras.index(split_view_id(v)[0]))
        ref, ref_cam = vs[0], split_view_id(vs[0])[0]
        cov = robot_pose_noise_covariance(ee_T_cam_init[ref_cam], np.radians(noise.robot_sigma_deg),
                                          noise.robot_sigma_mm * 1e-3)
        graph.add(factors.make_robot_pose_factor(base_T_ee[frame], [keys.hand_eye(ref_cam), keys.pose(ref)],
                                                 gtsam.noiseModel.Gaussian.Covariance(cov)))
        for v in vs[1:]:
            cam = split_view_id(v)[0]
            graph.add(factors.make_rigidity_factor([keys.hand_eye(ref_cam), keys.hand_eye(cam),
                                                    keys.pose(ref), keys.pose(v)], rig_noise))


def robot_chi2(keys, views, base_T_ee, values, noise: NoiseOptions) -> tuple[float, int]:
    """(sum of whitened squared robot-pose residuals, number of frames) at ``values``, with the
    same reference-view choice and noise as :func:`add_robot_factors`."""
    graph = gtsam.NonlinearFactorGraph()
    add_robot_factors(graph, keys, views, base_T_ee,
                      {c: values.atPose3(keys.hand_eye(c)) for c in keys.cameras if values.exists(keys.hand_eye(c))},
                      noise)
    robot = [graph.at(i) for i in range(graph.size()) if graph.at(i).dim() == 6 and len(graph.at(i).keys()) == 2]
    return 2.0 * sum(f.error(values) for f in robot), len(robot)


def add_scale_gauge_factors(graph, keys, views, noise: NoiseOptions):
    by_cam = {}
    for v in views:
        by_cam.setdefault(split_view_id(v)[0], []).append(v)
    for cam, vs in by_cam.items():
        graph.add(factors.make_scale_gauge_factor([keys.metric(cam)] + [keys.scale(v) for v in vs],
                                                  gtsam.noiseModel.Isotropic.Sigma(1, noise.scale_gauge_sigma)))


def add_depth_correction_priors(graph, keys, views, noise: NoiseOptions):
    """Zero-mean prior on each view's depth correction: smooth errors of a few percent."""
    if noise.depth_correction_sigma <= 0:
        return
    model = gtsam.noiseModel.Isotropic.Sigma(DEPTH_CORRECTION_DIM, noise.depth_correction_sigma)
    for v in views:
        graph.add(gtsam.PriorFactorVector(keys.correction(v), np.zeros(DEPTH_CORRECTION_DIM), model))


def initial_values(keys, init, with_correction=True) -> gtsam.Values:
    values = gtsam.Values()
    for v, T in init.base_T_cam.items():
        values.insert(keys.pose(v), T)
        values.insert(keys.scale(v), float(init.depth_scale[v]))
        if with_correction:
            values.insert(keys.correction(v), np.zeros(DEPTH_CORRECTION_DIM))
    for cam, X in init.ee_T_cam.items():
        values.insert(keys.hand_eye(cam), X)
        scales = [init.depth_scale[v] for v in init.base_T_cam if split_view_id(v)[0] == cam]
        values.insert(keys.metric(cam), float(np.exp(np.mean(np.log(scales)))))
    return values


def depth_correction(values, keys, v):
    k = keys.correction(v)
    return values.atVector(k) if values.exists(k) else np.zeros(DEPTH_CORRECTION_DIM)


def match_residuals(observations, values, keys) -> list:
    """Unwhitened per-match residuals e_p (N, 3) of every pair at ``values``."""
    out = []
    for o in observations:
        m = Match3DMeasurement(o.pts_a, o.pts_b, np.zeros((len(o), 3, 3)), o.basis_a, o.basis_b)
        out.append(match3d_residuals(m, values.atPose3(keys.pose(o.view_a)), values.atPose3(keys.pose(o.view_b)),
                                     values.atDouble(keys.scale(o.view_a)), values.atDouble(keys.scale(o.view_b)),
                                     depth_correction(values, keys, o.view_a), depth_correction(values, keys, o.view_b)))
    return out
