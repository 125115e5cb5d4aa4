"""Pattern-based reference methods: chessboard detection + PnP, OpenCV's five closed-form
hand-eye solvers, and ``pattern-ba`` — the strongest pattern method: a joint
reprojection adjustment over every camera's ee_T_cam, the board pose in the base frame
and each view's pose, where each view is tied to its robot pose by the robot pose factor
(robot noise), so noisy robot poses are absorbed rather than trusted."""

import logging
from dataclasses import dataclass

import cv2
import gtsam
import numpy as np

import factors
from calib3r_graph.errors import SolveError
from calib3r_graph.geometry import mean_pose
from factors.hand_eye import robot_pose_noise_covariance
from factors.pattern import PatternMeasurement, make_pattern_factor

log = logging.getLogger(__name__)

# A printed board's scale error, 1 sigma: prints are routinely 0.1-0.5 % off their nominal size.
BOARD_SCALE_TOLERANCE = 0.003

OPENCV_METHODS = {"tsai": cv2.CALIB_HAND_EYE_TSAI, "park": cv2.CALIB_HAND_EYE_PARK,
                  "horaud": cv2.CALIB_HAND_EYE_HORAUD, "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
                  "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS}


@dataclass
class Detection:
    frame: str
    uv: np.ndarray  # (N, 2) corners as detected (distorted pixels)
    cam_T_board: gtsam.Pose3  # from PnP
    reprojection_px: float
    ids: np.ndarray | None = None  # indices of uv into board_points (None: all of them, in order)


def board_points(pattern) -> np.ndarray:
    """(N, 3) points of the dataset's board (any kind in calib3r_graph.io.boards), metres."""
    from calib3r_graph.io import boards

    return boards.points(boards.from_pattern(pattern))


def detect(ds, camera: str, frames=None) -> list:
    """Board points and PnP pose in every image of a camera where the board is found (a
    checkerboard or circle grid whole, a ChArUco board in part: see Detection.ids)."""
    from calib3r_graph.io import board_turns, boards

    if not ds.pattern:
        raise SolveError("no pattern in dataset.yaml")
    cam = ds.cameras[camera]
    board = boards.from_pattern(ds.pattern, ds.root / "dataset.yaml")
    obj_all = boards.points(board)
    images = [(f, p) for f in frames or ds.frames if (p := ds.image_path(camera, f)) is not None]
    if board.kind == "charuco" and not board.dictionary and images:  # found from the first images
        grays = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for _, p in images[:10]]
        board = boards.resolve_dictionary(board, [g for g in grays if g is not None])
    out = []
    for f, path in images:
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        found = None if gray is None else boards.detect(gray, board)
        if found is None:
            continue
        uv, ids = found
        obj = obj_all if ids is None else obj_all[ids]
        ok, rvec, tvec = cv2.solvePnP(obj, uv, cam.K, cam.dist, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            continue
        proj, _ = cv2.projectPoints(obj, rvec, tvec, cam.K, cam.dist)
        err = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - uv) ** 2, 1))))
        R, _ = cv2.Rodrigues(rvec)
        out.append(Detection(f, uv, gtsam.Pose3(gtsam.Rot3(R), tvec.ravel()), err, ids))
    # a board that looks the same turned by 180°: each image's corner order from the robot's motion
    return board_turns.unturn_detections(board, out, ds.base_T_ee, cam.K, cam.dist, ds.root / "dataset.yaml")


def camera_intrinsics(cam) -> np.ndarray:
    """The OPENCV model's eight parameters of a camera (PINHOLE: no distortion), FULL_OPENCV's twelve."""
    return np.array(cam.params if cam.model == "FULL_OPENCV" else [*cam.params[:4], *cam.dist[:4]], dtype=float)


def opencv_hand_eye(ds, detections, method: str) -> gtsam.Pose3:
    if len(detections) < 3:
        raise SolveError(f"the board is found in only {len(detections)} images (3 needed)")
    R_g2b, t_g2b, R_t2c, t_t2c = [], [], [], []
    for d in detections:
        E = ds.base_T_ee[d.frame]
        R_g2b.append(E.rotation().matrix())
        t_g2b.append(E.translation())
        R_t2c.append(d.cam_T_board.rotation().matrix())
        t_t2c.append(d.cam_T_board.translation())
    R, t = cv2.calibrateHandEye(R_g2b, t_g2b, R_t2c, t_t2c, method=OPENCV_METHODS[method])
    return gtsam.Pose3(gtsam.Rot3(R), t.ravel())


HELD = 1e-6  # a prior this tight holds a lens coefficient at its given value


def lens_sigmas(cam) -> np.ndarray:
    """The prior sigmas of a camera's lens coefficients in pattern_ba: 0.5 on k1 and k2, 0.01 on p1 and
    p2 (OPENCV, FULL_OPENCV); FULL_OPENCV's k3 and rational k4-k6 are held at their given values, and
    PINHOLE stays a pinhole.

    Why k3-k6 are held (a FULL_OPENCV camera's come from a file, a factory model or a full
    calibration, which a board's views rarely improve on): on 25 simulated views of a 9x6 board
    0.3-0.6 m from a 640x480 camera with f = 460 px and a RealSense-like k3 = -0.0236 (board in
    the middle of the image, 3-4 seeds), refining k3 under a 0.5 prior spreads it over -0.18 to
    -0.04, under a 0.05 prior biases it to -0.03 to -0.06, and refining k4-k6 too makes them
    non-zero, while the hand-eye moves by under 0.02 mm. On 9 rendered views with the board in
    the image's corners (tests/test_user_formats.py), refining k3 lands at -0.0221 and k4-k6 at
    -0.010, 0.011, 0.002 (truth 0), moving the hand-eye from 0.67 to 0.70 mm off the truth. Only a
    wrong given k3 is helped (given 0: 1.18 mm held, 0.70 mm refined), and a 4-coefficient model
    stays OPENCV, whose k1, k2 are refined as before.
    """
    if cam.model == "PINHOLE":
        return np.full(4, HELD)
    return np.r_[0.5, 0.5, 0.01, 0.01, np.full(4 if cam.model == "FULL_OPENCV" else 0, HELD)]


@dataclass
class PatternBAResult:
    ee_T_cam: dict  # camera -> Pose3
    intrinsics: dict  # camera -> [fx, fy, cx, cy, k1, k2, p1, p2] (FULL_OPENCV: and k3, k4, k5, k6)
    covariance: dict  # camera -> 6x6 of ee_T_cam (GTSAM tangent): model + systematic + board scale; {} if unobservable
    corner_sigma_px: float = 0.5  # calibrated corner noise
    robot_noise_factor: float = 1.0  # robot sigma used / nominal
    board_scale: float = 1.0  # estimated square size / nominal
    board_scale_sigma: float = 0.0  # the used scale's sigma (0 when held fixed)
    chi2: dict = None  # {"corners": chi2, "robot": chi2} of the final solve, with the noise it used
    covariance_model: dict = None  # camera -> 6x6 marginal of the noise model alone (covariance adds the rest)
    board_scale_estimate: dict = None  # the robot's measurement of the scale and how it was combined
    systematic: dict = None  # camera -> the kinematic error field's summary (systematic.py)
    intrinsics_sigma: dict = None  # camera -> posterior 1-sigma of intrinsics' entries ({} if not refined/unobservable)


def pattern_ba(ds, detections_by_cam: dict, noise, init_ee_T_cam: dict, sigma_px=0.5, iterations=100,
               refine_intrinsics=True, noise_rounds=4, estimate_board_scale=True,
               board_scale_tolerance=BOARD_SCALE_TOLERANCE) -> "PatternBAResult":
    """Joint adjustment over every camera that saw the board.

    With ``refine_intrinsics`` each camera's OPENCV model (fx, fy, cx, cy, k1, k2, p1, p2) is
    adjusted too, on the raw corners, under a weak prior at the given values (3 % of f, 2 % of
    the image size, 0.5 on k1 and k2, 0.01 on p1 and p2; a FULL_OPENCV camera's k3-k6 are held
    at their given values, see lens_sigmas): the robot's metric motion
    separates focal length from board distance, which a board-only calibration cannot do
    when the board is small and far. The distortion is refined with the focal length and
    principal point because it acts on normalised coordinates: new K with old distortion
    coefficients is a different lens.

    With ``estimate_board_scale`` the board's scale is a variable too (one factor on the
    nominal square size): a printed board is routinely 0.1-0.5 % off, which biases a pattern
    hand-eye along the optical axis by that fraction of the board distance, and the robot's
    metric motion can measure it. How well depends on the motion: when the camera orbits the
    board, a scale change and a shift of ee_T_cam along the optical axis are nearly the same
    thing, and a systematic robot error of a fraction of a millimetre moves the estimate by
    percent. So the robot's measurement ``s_data`` is taken with its statistical sigma and the
    systematic sigma of the kinematic error field (systematic.py) and combined with the
    nominal size, whose sigma is ``board_scale_tolerance`` (a print's typical error):
    ``s = 1 + w (s_data - 1)``, ``w = tol^2 / (tol^2 + sigma_data^2)``. The final solve holds the
    scale there, and its remaining sigma is added to the covariance along the direction in
    which the scale moves ee_T_cam (the regression of ee_T_cam on the scale).

    The two noise groups are calibrated from their own residuals (variance component
    estimation), because their relative weight decides the result: each round rescales the
    corner noise by its a posteriori variance factor (up or down: ``sigma_px`` is only the
    starting value; subpixel corners are often 0.05-0.1 px) and the robot noise by its own
    (inflated only: never better than the nominal sigma), then solves again, until both
    factors settle within 5 %.
    """
    obj = board_points(ds.pattern)
    k_board, k_scale = gtsam.symbol("b", 0), gtsam.symbol("q", 0)
    cams = [c for c in detections_by_cam if detections_by_cam[c]]
    values = gtsam.Values()
    boards = []
    for j, c in enumerate(cams):
        values.insert(gtsam.symbol("e", j), init_ee_T_cam[c])
        for d in detections_by_cam[c]:
            boards.append(ds.base_T_ee[d.frame].compose(init_ee_T_cam[c]).compose(d.cam_T_board))
    values.insert(k_board, mean_pose(boards))
    if estimate_board_scale:
        values.insert(k_scale, 1.0)
    for j, c in enumerate(cams):
        values.insert(gtsam.symbol("k", j), camera_intrinsics(ds.cameras[c]))
    views = [(j, c, d) for j, c in enumerate(cams) for d in detections_by_cam[c]]
    for i, (j, c, d) in enumerate(views):
        values.insert(gtsam.symbol("v", i), ds.base_T_ee[d.frame].compose(init_ee_T_cam[c]))

    def build(px, robot_scale, scale_prior=(1.0, 0.02)):
        graph = gtsam.NonlinearFactorGraph()
        board, robot = [], []
        if estimate_board_scale:
            graph.add(gtsam.PriorFactorDouble(k_scale, scale_prior[0], gtsam.noiseModel.Isotropic.Sigma(1, scale_prior[1])))
        if refine_intrinsics:  # weak prior at the given intrinsics
            for j, c in enumerate(cams):
                cam = ds.cameras[c]
                sig = [0.03 * cam.K[0, 0], 0.03 * cam.K[1, 1], 0.02 * cam.width, 0.02 * cam.height, *lens_sigmas(cam)]
                graph.add(gtsam.PriorFactorVector(gtsam.symbol("k", j), camera_intrinsics(cam),
                                                  gtsam.noiseModel.Diagonal.Sigmas(np.array(sig))))
        for i, (j, c, d) in enumerate(views):
            k_cam = gtsam.symbol("v", i)
            keys = [k_board, k_cam] + ([gtsam.symbol("k", j)] if refine_intrinsics else []) + \
                ([k_scale] if estimate_board_scale else [])
            pts = obj if d.ids is None else obj[d.ids]  # a ChArUco detection holds some of the corners
            board.append(make_pattern_factor(PatternMeasurement(pts, d.uv, camera_intrinsics(ds.cameras[c]), px,
                                                                estimate_board_scale),
                                             keys))
            cov = robot_pose_noise_covariance(init_ee_T_cam[c], np.radians(noise.robot_sigma_deg),
                                              noise.robot_sigma_mm * 1e-3) * robot_scale
            robot.append(factors.make_robot_pose_factor(ds.base_T_ee[d.frame], [gtsam.symbol("e", j), k_cam],
                                                        gtsam.noiseModel.Gaussian.Covariance(cov)))
        for f in board + robot:
            graph.add(f)
        return graph, board, robot

    # Redundancy of each group: the corners fix each view's pose (and the intrinsics); the
    # robot factors then over-determine the views beyond ee_T_cam and the board pose.
    n_corners = sum(len(d.uv) for _, _, d in views)
    free = sum(4 + int(np.sum(lens_sigmas(ds.cameras[c]) > HELD)) for c in cams) * refine_intrinsics
    redundancy_board = max(2 * n_corners - 6 * len(views) - free - estimate_board_scale, 1)
    redundancy_robot = max(6 * len(views) - 6 * len(cams) - 6, 1)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    px, robot_scale, settled = sigma_px, 1.0, False
    for rnd in range(noise_rounds + 1):
        graph, board, robot = build(px, robot_scale)
        values = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        if settled or rnd == noise_rounds:  # this solve used the settled noise
            break
        board_factor = 2 * sum(f.error(values) for f in board) / redundancy_board
        robot_factor = 2 * sum(f.error(values) for f in robot) / redundancy_robot
        new_px, new_robot = px * np.sqrt(board_factor), max(1.0, robot_scale * robot_factor)
        settled = abs(new_px / px - 1) < 0.05 and abs(new_robot / robot_scale - 1) < 0.05
        px, robot_scale = new_px, new_robot

    def systematic(graph, values, with_scale):
        from calib3r_graph.solver.systematic import systematic_errors

        robot = [(gtsam.symbol("e", j), gtsam.symbol("v", i), ds.base_T_ee[d.frame]) for i, (j, _, d) in enumerate(views)]
        return systematic_errors(graph, values, robot, {c: (gtsam.symbol("e", j), k_scale if with_scale else None)
                                                        for j, c in enumerate(cams)})

    scale_info, scale_term = {}, {}
    if estimate_board_scale:
        try:  # the robot's measurement of the scale, and how ee_T_cam moves with it
            marginals = gtsam.Marginals(graph, values)
            sigma_stat = float(np.sqrt(marginals.marginalCovariance(k_scale)[0, 0]))
            slope = {}
            for j, c in enumerate(cams):
                J = marginals.jointMarginalCovariance(gtsam.KeyVector([gtsam.symbol("e", j), k_scale])).fullMatrix()
                slope[c] = J[:6, 6] / J[6, 6]  # d xi / d s
        except RuntimeError:
            sigma_stat, slope = float("inf"), {}
        s_data = values.atDouble(k_scale)
        sigma_sys = float(np.sqrt(np.mean([e.scale_sigma_rel ** 2 for e in systematic(graph, values, True).values()])))
        sigma_data = float(np.hypot(sigma_stat, sigma_sys))
        w = board_scale_tolerance ** 2 / (board_scale_tolerance ** 2 + sigma_data ** 2)
        s_post = 1.0 + w * (s_data - 1.0)
        sigma_post = float(np.sqrt(1.0 / (1.0 / board_scale_tolerance ** 2 + 1.0 / sigma_data ** 2)))
        scale_info = {"measured": s_data, "measured_sigma_statistical": sigma_stat,
                      "measured_sigma_systematic": sigma_sys, "nominal_tolerance": board_scale_tolerance,
                      "weight_of_measurement": w, "used": s_post, "used_sigma": sigma_post}
        log.info("pattern-ba: the robot measures the board scale %.5f ± %.5f (statistical %.5f, systematic %.5f); "
                 "with the nominal size (± %.4f): %.5f ± %.5f", s_data, sigma_data, sigma_stat, sigma_sys,
                 board_scale_tolerance, s_post, sigma_post)
        graph, board, robot = build(px, robot_scale, (s_post, 1e-7))
        values = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        scale_term = {c: sigma_post ** 2 * np.outer(g, g) for c, g in slope.items()}
    board_scale = values.atDouble(k_scale) if estimate_board_scale else 1.0
    chi2 = {"corners": 2 * sum(f.error(values) for f in board), "robot": 2 * sum(f.error(values) for f in robot)}
    log.info("pattern-ba: corner noise %.3f px, robot poses %.1fx their nominal sigma, board scale %.5f (square "
             "%.3f mm)", px, np.sqrt(robot_scale), board_scale,
             1e3 * board_scale * ds.pattern.get("square_size", ds.pattern.get("spacing", np.nan)))
    intrinsics = {c: values.atVector(gtsam.symbol("k", j)) for j, c in enumerate(cams)}
    board_scale_sigma = scale_info.get("used_sigma", 0.0)
    try:
        marginals = gtsam.Marginals(graph, values)
        covariance_model = {c: marginals.marginalCovariance(gtsam.symbol("e", j)) for j, c in enumerate(cams)}
        intrinsics_sigma = {c: np.sqrt(np.diag(marginals.marginalCovariance(gtsam.symbol("k", j))))
                            for j, c in enumerate(cams)} if refine_intrinsics else {}
    except RuntimeError:  # an unobservable direction: report no covariance rather than fail
        covariance_model, intrinsics_sigma = {}, {}
    sys_err = systematic(graph, values, False) if covariance_model else {}
    covariance = {c: C + sys_err[c].covariance + scale_term.get(c, 0.0) for c, C in covariance_model.items()}
    for c, k in intrinsics.items():
        if refine_intrinsics:
            sig = intrinsics_sigma.get(c, np.full(len(k), np.nan))
            log.info("pattern-ba: %s intrinsics fx %.1f±%.1f fy %.1f±%.1f cx %.1f±%.1f cy %.1f±%.1f, k1 %.4f±%.4f "
                     "k2 %.4f±%.4f p1 %.5f±%.5f p2 %.5f±%.5f" + " k%d %.4f±%.4f" * (len(k) - 8), c,
                     *np.ravel(np.column_stack([k, sig])[:8]),
                     *[x for i in range(8, len(k)) for x in (i - 4, k[i], sig[i])])
    return PatternBAResult({c: values.atPose3(gtsam.symbol("e", j)) for j, c in enumerate(cams)}, intrinsics,
                           covariance, px, float(np.sqrt(robot_scale)), board_scale, board_scale_sigma, chi2,
                           covariance_model, scale_info, {c: e.to_json() for c, e in sys_err.items()},
                           intrinsics_sigma)
