"""pattern-ba, the pattern reference: its two noise groups (corner pixels, robot poses) are
calibrated from their own residuals, so neither an optimistic robot nor a pessimistic corner
sigma decides the result."""

from pathlib import Path

import cv2
import gtsam
import numpy as np
import pytest

from calib3r_graph.evaluation.pattern import Detection, board_points, camera_intrinsics, opencv_hand_eye, pattern_ba
from calib3r_graph.io.dataset import Camera, Dataset
from calib3r_graph.solver.graph import NoiseOptions


def synthetic_board_recording(corner_px, robot_mm, robot_deg, n=25, seed=0, printed_scale=1.0, cam=None,
                              distance=(0.45, 0.8), field_mm_per_m=0.0):
    """A 9x6 board 0.45-0.8 m in front of an eye-in-hand camera, seen from n flange poses; the
    board as printed is ``printed_scale`` times its nominal size. The distance varies: without
    that, the board's scale and the hand-eye translation along the optical axis are nearly one
    direction (every method then leans on the nominal square size). ``cam``: the true camera
    (default a 600 px pinhole). ``field_mm_per_m``: a systematic robot error, the measured flange
    positions off by ``L (p - p_mean)`` with L's entries drawn at that rms (a kinematic error)."""
    rng = np.random.default_rng(seed)
    pattern = {"type": "checkerboard", "inner_corners": [9, 6], "square_size": 0.03}
    cam = cam or Camera("cam0", "PINHOLE", 640, 480, (600.0, 600.0, 320.0, 240.0))
    ee_T_cam = gtsam.Pose3(gtsam.Rot3.Ypr(1.5, 0.05, -0.1), np.array([0.03, -0.05, 0.08]))
    base_T_board = gtsam.Pose3(gtsam.Rot3.Ypr(0.2, 0.0, np.pi), np.array([0.6, 0.0, 0.0]))
    centre = base_T_board.transformFrom(np.array([0.12, 0.075, 0.0]))
    obj = board_points(pattern)
    truth, measured, dets = {}, {}, []
    for i in range(n):
        f = f"{i:04d}"
        # Look at the board centre from 0.45-0.8 m, with varied viewing directions and roll.
        d = np.array([0.0, 0.0, 1.0]) + rng.normal(scale=0.35, size=3) * [1, 1, 0]
        eye = centre + rng.uniform(*distance) * d / np.linalg.norm(d)
        z = (centre - eye) / np.linalg.norm(centre - eye)
        x = np.cross(rng.normal(size=3), z)
        x /= np.linalg.norm(x)
        base_T_cam = gtsam.Pose3(gtsam.Rot3(np.c_[x, np.cross(z, x), z]), eye)
        truth[f] = base_T_cam.compose(ee_T_cam.inverse())
        noise = np.r_[rng.normal(scale=np.radians(robot_deg), size=3), rng.normal(scale=robot_mm * 1e-3, size=3)]
        measured[f] = truth[f].retract(noise)
        cam_T_board = base_T_cam.between(base_T_board)
        pc = np.array([cam_T_board.transformFrom(printed_scale * p) for p in obj])
        uv = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), cam.K, cam.dist)[0].reshape(-1, 2)
        dets.append(Detection(f, uv + rng.normal(scale=corner_px, size=uv.shape), cam_T_board, 0.0))
    if field_mm_per_m:
        L = rng.normal(scale=field_mm_per_m * 1e-3, size=(3, 3))
        mean = np.mean([T.translation() for T in truth.values()], axis=0)
        measured = {f: gtsam.Pose3(T.rotation(), T.translation() + L @ (truth[f].translation() - mean))
                    for f, T in measured.items()}
    ds = Dataset(Path("."), {"cam0": cam}, measured, pattern)
    return ds, dets, ee_T_cam


@pytest.mark.parametrize("corner_px, robot_factor", [(0.08, 3.0), (0.6, 1.0)])
def test_pattern_ba_calibrates_corner_and_robot_noise(corner_px, robot_factor):
    noise = NoiseOptions()
    ds, dets, truth = synthetic_board_recording(corner_px, noise.robot_sigma_mm * robot_factor,
                                                noise.robot_sigma_deg * robot_factor)
    init = {"cam0": opencv_hand_eye(ds, dets, "park")}
    res = pattern_ba(ds, {"cam0": dets}, noise, init, sigma_px=0.5, refine_intrinsics=False)
    assert res.corner_sigma_px == pytest.approx(corner_px, rel=0.15)
    assert res.robot_noise_factor == pytest.approx(robot_factor, rel=0.3)
    X = res.ee_T_cam["cam0"]
    assert np.linalg.norm(X.translation() - truth.translation()) < 1.5e-3 * max(1.0, corner_px / 0.2)
    # The error is within what the calibrated covariance says (99.9 % of chi2 with 6 dof).
    xi = gtsam.Pose3.Logmap(X.between(truth))
    assert xi @ np.linalg.solve(res.covariance["cam0"], xi) < 22.5


def test_pattern_ba_measures_a_misprinted_board():
    """A board printed 0.4 % too large biases every method that trusts its nominal size along
    the optical axis (0.4 % of the board distance: 2-3 mm); pattern-ba measures the scale
    against the robot's metric motion and is unbiased."""
    noise = NoiseOptions()
    ds, dets, truth = synthetic_board_recording(0.08, noise.robot_sigma_mm, noise.robot_sigma_deg, n=30, seed=2,
                                                printed_scale=1.004)
    init = {"cam0": opencv_hand_eye(ds, dets, "park")}
    fixed = pattern_ba(ds, {"cam0": dets}, noise, init, refine_intrinsics=False, estimate_board_scale=False)
    res = pattern_ba(ds, {"cam0": dets}, noise, init, refine_intrinsics=False)
    assert res.board_scale == pytest.approx(1.004, abs=5e-4)
    err = lambda X: np.linalg.norm(X.translation() - truth.translation())
    assert err(fixed.ee_T_cam["cam0"]) > 1.5e-3
    assert err(res.ee_T_cam["cam0"]) < 0.5e-3


def test_pattern_ba_refines_the_whole_lens_model():
    """Given intrinsics 2 % off in focal length, 6 px off in the principal point and with a
    weaker k1 (a board-only calibration of a small board), pattern-ba adjusts the whole OPENCV
    model on the raw corners with the robot and lands on the true camera and hand-eye."""
    noise = NoiseOptions()
    true_cam = Camera("cam0", "OPENCV", 640, 480, (600.0, 602.0, 318.0, 245.0, -0.25, 0.12, 1e-3, -5e-4))
    ds, dets, truth = synthetic_board_recording(0.08, noise.robot_sigma_mm, noise.robot_sigma_deg, n=30, seed=4,
                                                cam=true_cam)
    given = Camera("cam0", "OPENCV", 640, 480, (612.0, 614.0, 324.0, 239.0, -0.2, 0.1, 0.0, 0.0))
    ds.cameras["cam0"] = given
    init = {"cam0": opencv_hand_eye(ds, dets, "park")}
    res = pattern_ba(ds, {"cam0": dets}, noise, init, estimate_board_scale=False)
    k = res.intrinsics["cam0"]
    np.testing.assert_allclose(k[:2], camera_intrinsics(true_cam)[:2], atol=0.5)  # focal length, px
    np.testing.assert_allclose(k[2:4], camera_intrinsics(true_cam)[2:4], atol=1.0)  # principal point, px
    assert k[4] == pytest.approx(-0.25, abs=0.01)
    X = res.ee_T_cam["cam0"]
    assert np.linalg.norm(X.translation() - truth.translation()) < 1.5e-3
    # The principal point and the hand-eye rotation are nearly one direction (1 px = 0.1 deg here).
    assert np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(X.rotation().between(truth.rotation())))) < 0.1
    xi = gtsam.Pose3.Logmap(X.between(truth))
    assert xi @ np.linalg.solve(res.covariance["cam0"], xi) < 22.5
    # With the given intrinsics held fixed the same data is centimetres off: the test has teeth.
    fixed = pattern_ba(ds, {"cam0": dets}, noise, init, refine_intrinsics=False, estimate_board_scale=False)
    assert np.linalg.norm(fixed.ee_T_cam["cam0"].translation() - truth.translation()) > 5e-3


def test_pattern_ba_keeps_the_nominal_scale_when_the_motion_cannot_measure_it():
    """rwhe_kuka_2's case: the camera orbits the board at a nearly constant distance, so the
    board's scale and the hand-eye along the optical axis are nearly one direction, and a
    kinematic error of 2 mm/m across the workspace moves the robot's measurement of the scale
    by percent. pattern-ba weighs that measurement by its statistical and systematic sigma
    against the nominal size (0.3 % print tolerance): it stays near the nominal scale, lands
    near the truth, and its total covariance covers the error."""
    noise = NoiseOptions()
    ds, dets, truth = synthetic_board_recording(0.05, 0.05, 0.005, n=28, seed=3, distance=(0.49, 0.51),
                                                field_mm_per_m=2.0)
    init = {"cam0": opencv_hand_eye(ds, dets, "park")}
    res = pattern_ba(ds, {"cam0": dets}, noise, init, refine_intrinsics=False)
    est = res.board_scale_estimate
    assert abs(est["measured"] - 1) > 0.01, est  # the robot alone is percent off: the test has teeth
    assert est["measured_sigma_systematic"] > est["measured_sigma_statistical"], est
    assert abs(res.board_scale - 1) < 0.003 and res.board_scale_sigma < 0.003, est
    X = res.ee_T_cam["cam0"]
    assert np.linalg.norm(X.translation() - truth.translation()) < 3e-3
    xi = gtsam.Pose3.Logmap(X.between(truth))
    assert xi @ np.linalg.solve(res.covariance["cam0"], xi) < 22.5
    # The noise model alone does not cover it.
    assert xi @ np.linalg.solve(res.covariance_model["cam0"], xi) > 22.5
