"""The systematic part of the covariance: a kinematic error field measured from the robot
residuals (calib3r_graph/solver/systematic.py). Seeded synthetic motions; tolerances in mm."""

import shutil

import gtsam
import numpy as np
import pytest

from calib3r_graph.io.dataset import load_dataset, load_ground_truth, read_robot_poses, write_robot_poses
from calib3r_graph.io.predictions import load_predictions
from calib3r_graph.solver.solve import SolveOptions, solve
from calib3r_graph.solver.systematic import measure_field
from tests.conftest import SAMPLE

EE_T_CAM = gtsam.Pose3(gtsam.Rot3.Ypr(1.4, 0.1, -1.6), np.array([0.03, -0.10, 0.08]))


def orbit(n, rng, distance=(0.45, 0.55)):
    """Flange poses whose camera looks at one point from n directions (rwhe_kuka_2's kind of motion)."""
    target = np.array([0.6, 0.2, 0.3])
    out = []
    for _ in range(n):
        d = np.array([-1.0, 0.0, 0.0]) + rng.normal(scale=0.3, size=3) * [0, 1, 1]
        eye = target + rng.uniform(*distance) * d / np.linalg.norm(d)
        z = (target - eye) / np.linalg.norm(target - eye)
        x = np.cross(rng.normal(size=3), z)
        x /= np.linalg.norm(x)
        base_T_cam = gtsam.Pose3(gtsam.Rot3(np.c_[x, np.cross(z, x), z]), eye)
        out.append(base_T_cam.compose(EE_T_CAM.inverse()))
    return out


def with_errors(base_T_ee, rng, field_mm_per_m, white_mm):
    """The same flange poses as measured: a linear error field L (p - p_mean) over the flange
    positions p plus white noise."""
    p = np.array([E.translation() for E in base_T_ee])
    L = rng.normal(scale=field_mm_per_m * 1e-3, size=(3, 3))
    err = (p - p.mean(0)) @ L.T + rng.normal(scale=white_mm * 1e-3, size=p.shape)
    return [gtsam.Pose3(E.rotation(), E.translation() + e) for E, e in zip(base_T_ee, err)]


def test_white_robot_noise_adds_nothing():
    """Independent per-pose noise is what the noise model already covers: no field is found."""
    taus, rots = [], []
    for seed in range(10):
        rng = np.random.default_rng(seed)
        truth = orbit(28, rng)
        cams = [E.compose(EE_T_CAM) for E in truth]
        tau, _ = measure_field(with_errors(truth, rng, 0.0, 0.2), cams, EE_T_CAM)
        taus.append(1e3 * tau[0, 0])
        rots.append(np.degrees(tau[1, 0]))
    assert np.median(taus) < 0.3  # mm/m; a real arm's field is 1-2 mm/m (rwhe recordings)
    assert np.median(rots) < 0.01  # deg/m


def test_field_is_measured_from_the_residual_it_leaves():
    """A field of 2 mm/m over the flange positions, with 0.1 mm of white noise, is measured from
    the part of it that the hand-eye, world offset and scale cannot absorb: within 25 % on
    average over seeds, and the white part comes out at its 0.1 mm."""
    taus, whites = [], []
    for seed in range(40):
        rng = np.random.default_rng(100 + seed)
        truth = orbit(28, rng)
        measured = with_errors(truth, rng, 2.0, 0.1)
        cams = [E.compose(EE_T_CAM) for E in truth]  # the visual trajectory: exact up to the world frame
        tau, white = measure_field(measured, cams, EE_T_CAM)
        taus.append(tau[0, 0] * 1e3)
        whites.append(white * 1e3)
    assert np.mean(taus) == pytest.approx(2.0, rel=0.25)
    assert np.median(whites) == pytest.approx(0.1, rel=0.3)


@pytest.mark.slow
def test_solve_reports_the_field_and_its_total_covers_the_error(tmp_path):
    """The sample with a 3 mm/m kinematic error added to its robot poses: solve measures the
    field, reports covariance = covariance_model + systematic, and the total covers the error
    against ground truth (chi2 with 6 dof, 99.9 %)."""
    root = tmp_path / "sample"
    shutil.copytree(SAMPLE, root)
    ds = load_dataset(root)
    poses = read_robot_poses(root / "robot_poses.csv", ds.robot_unit)
    frames = sorted(poses)
    rng = np.random.default_rng(5)
    moved = with_errors([poses[f] for f in frames], rng, 3.0, 0.0)
    write_robot_poses(root / "robot_poses.csv", dict(zip(frames, moved)), unit=ds.robot_unit)
    ds = load_dataset(root)
    # the field alone: 8 poses would also run the jackknife (test_jackknife.py)
    sol = solve(ds, load_predictions(root, "sim", ds.cameras, set(ds.frames)),
                SolveOptions(progress=False, jackknife="never"))
    gt = load_ground_truth(root)["hand_eye"]
    for c in sol.ee_T_cam:
        assert sol.systematic[c].gradient_mm_per_m > 0.5
        np.testing.assert_allclose(sol.covariance[c], sol.covariance_model[c] + sol.systematic[c].covariance)
        xi = gtsam.Pose3.Logmap(gt[c].between(sol.ee_T_cam[c]))
        assert xi @ np.linalg.solve(sol.covariance[c], xi) < 22.5
