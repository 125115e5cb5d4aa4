"""The camera model's share of the total sigma (calib3r_graph/solver/camera_model.py): the
intrinsics' stated 1-sigma propagated into ee_T_cam's covariance. A rendered scene whose
principal point is known; tolerances in mm and degrees."""

import gtsam
import numpy as np
import pytest
import yaml

from calib3r_graph.errors import InputError
from calib3r_graph.io.dataset import load_dataset
from calib3r_graph.io.predictions import load_predictions
from calib3r_graph.io.results import calibration_json, covariance_in_ee_frame, summary_text, tangent_in_ee_frame
from calib3r_graph.solver.camera_model import parse_intrinsics_sigma, with_moved_intrinsics, with_params_sigma
from calib3r_graph.solver.solve import SolveOptions, solve

SIGMA = (2.0, 2.0, 5.0, 5.0)  # fx, fy, cx, cy (px): a board calibration's principal point is often 3-6 px off
OPT = SolveOptions(progress=False, jackknife="never")


@pytest.fixture(scope="module")
def solved(simulated):
    root = simulated(seed=3, frames=8)
    ds = load_dataset(root)
    preds = load_predictions(root, "sim", ds.cameras, set(ds.frames))
    with_sigma = with_params_sigma(ds, SIGMA, "test")
    return ds, preds, solve(ds, preds, OPT), with_sigma, solve(with_sigma, preds, OPT)


def test_share_is_reported_with_params_sigma_and_absent_without(solved):
    """Without a stated sigma nothing is added and the summary says the camera model is not in
    the sigma; with one, its share is non-zero, reported beside the noise model's, and the total
    is the rest plus it (the same solution)."""
    ds, preds, plain, ds_sigma, sol = solved
    cal = calibration_json(plain, "sim")["cameras"]["cam0"]
    assert cal["camera_model"] == {"propagated": False, "why": pytest.approx(cal["camera_model"]["why"])}
    assert "covariance_camera_model" not in cal
    assert "camera model not in the sigma" in summary_text(plain, ds, "sim")

    cal = calibration_json(sol, "sim")["cameras"]["cam0"]
    share = np.array(cal["covariance_camera_model"])
    assert cal["camera_model"]["propagated"] and cal["camera_model"]["params_sigma_px"]["cx"] == 5.0
    assert cal["sigma_ee_frame_camera_model"]["x_mm"] + cal["sigma_ee_frame_camera_model"]["y_mm"] > 0.3
    np.testing.assert_allclose(np.array(cal["covariance"]), np.asarray(plain.covariance["cam0"]) + share,
                               atol=1e-12, rtol=1e-6)
    assert sol.metric_scale["cam0"][1] > plain.metric_scale["cam0"][1]
    line = next(x for x in summary_text(sol, ds_sigma, "sim").splitlines() if "of which" in x)
    assert "noise model" in line and "camera model t = [" in line and "± 2 2 5 5 px" in line


def test_linearised_shift_matches_a_resolve_and_the_total_covers_it(solved):
    """Moving cx by its 1-sigma and solving again moves ee_T_cam as the linearisation predicts
    (within 20 %), and the total sigma covers that shift (at most 3 sigma per axis), which the
    total without the camera model does not."""
    ds, preds, plain, ds_sigma, sol = solved
    X = sol.ee_T_cam["cam0"]
    R = X.rotation().matrix()
    moved = solve(*with_moved_intrinsics(ds_sigma, preds, "cam0", "cx", SIGMA[2]), OPT)
    real = gtsam.Pose3.Logmap(X.between(moved.ee_T_cam["cam0"]))
    predicted = sol.camera_model["cam0"].shift_per_sigma["cx"]
    for part in (slice(0, 3), slice(3, 6)):  # rotation, translation
        assert np.linalg.norm(predicted[part] - real[part]) <= 0.2 * np.linalg.norm(real[part])
    shift = np.array(list(tangent_in_ee_frame(R, real).values()))  # deg, mm in the ee frame
    assert np.abs(shift[3:]).max() > 0.5  # mm: a shift the sigma must show

    def sigmas(cov):
        s = np.sqrt(np.diag(covariance_in_ee_frame(X, np.asarray(cov))))
        return np.r_[np.degrees(s[:3]), s[3:] * 1e3]

    assert np.all(np.abs(shift) <= 3 * sigmas(sol.covariance["cam0"]))
    assert np.any(np.abs(shift) > 3 * sigmas(plain.covariance["cam0"]))  # today's total misses it


def test_params_sigma_in_dataset_yaml(tmp_path, simulated):
    """dataset.yaml's optional per-camera params_sigma is read, written back, and refused with the
    file and the camera named when it is not four numbers >= 0; --intrinsics-sigma-px's F,C too."""
    import shutil

    from calib3r_graph.io.dataset import camera_to_yaml

    root = tmp_path / "sim"
    shutil.copytree(simulated(seed=3, frames=8), root)
    meta = yaml.safe_load((root / "dataset.yaml").read_text())
    assert load_dataset(root).cameras["cam0"].params_sigma is None  # absent: not stated
    meta["cameras"][0]["params_sigma"] = [1.5, 1.5, 3, 4]
    (root / "dataset.yaml").write_text(yaml.safe_dump(meta))
    cam = load_dataset(root).cameras["cam0"]
    assert cam.params_sigma == (1.5, 1.5, 3.0, 4.0)
    assert camera_to_yaml(cam)["params_sigma"] == [1.5, 1.5, 3.0, 4.0]
    for bad in ([1, 2, 3], [1, 2, 3, -1], "x"):
        meta["cameras"][0]["params_sigma"] = bad
        (root / "dataset.yaml").write_text(yaml.safe_dump(meta))
        with pytest.raises(InputError, match="params_sigma must be four numbers") as e:
            load_dataset(root)
        assert "dataset.yaml" in str(e.value) and "cam0" in str(e.value)
    assert parse_intrinsics_sigma("5,3") == (5.0, 5.0, 3.0, 3.0)
    for bad in ("5", "a,b", "-1,2", "nan,1"):
        with pytest.raises(InputError, match="--intrinsics-sigma-px"):
            parse_intrinsics_sigma(bad)


def test_board_calibration_gives_the_intrinsics_sigma():
    """import's board calibration returns the intrinsics' 1-sigma (OpenCV's stdDeviationsIntrinsics)
    for dataset.yaml's params_sigma: projected corners of a 9x6 board (30 mm) in 12 poses with 0.1 px
    noise; the sigma is positive, shrinks with less noise, and the error is within 4 sigma."""
    import cv2

    from calib3r_graph.importers import as_board, calibrate_intrinsics

    board = as_board("9x6", 0.03)
    obj = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * 0.03
    obj = np.c_[obj - obj.mean(0), np.zeros(len(obj))]
    K = np.array([[520.0, 0, 322.5], [0, 520.0, 237.5], [0, 0, 1]])
    rng = np.random.default_rng(0)
    sigmas = []
    for noise_px in (0.1, 0.02):
        dets = {}
        for i in range(12):
            rvec = rng.normal(scale=0.35, size=3)
            tvec = np.array([*rng.normal(scale=0.04, size=2), rng.uniform(0.35, 0.6)])
            uv, _ = cv2.projectPoints(obj, rvec, tvec, K, np.zeros(4))
            uv = uv.reshape(-1, 2) + np.random.default_rng(i).normal(scale=noise_px, size=(len(obj), 2))
            dets[f"{i:04d}"] = (uv.astype(np.float32), None)
        K_est, _, _, _, sigma = calibrate_intrinsics(dets, board, (640, 480), with_sigma=True)
        err = np.array([K_est[0, 0], K_est[1, 1], K_est[0, 2], K_est[1, 2]]) - [520.0, 520.0, 322.5, 237.5]
        assert len(sigma) == 4 and all(s > 0 for s in sigma)
        assert np.all(np.abs(err) <= 4 * np.array(sigma))
        sigmas.append(np.array(sigma))
    assert np.all(sigmas[1] < sigmas[0] / 2)
