"""Evaluation against ground truth, with the paper's metrics.

e_t: Euclidean distance between the estimated and true ee_T_cam translations (m);
e_theta: angle of the rotation between them (rad).
"""

import json
from pathlib import Path

import gtsam
import numpy as np

from calib3r_graph.dataset import ee_T_cam_by_camera, load_ground_truth
from calib3r_graph.errors import InputError
from calib3r_graph.geometry import pose_error


def hand_eye_errors(T_ee_cam: dict, ground_truth: dict) -> dict:
    """{camera: {"e_t_m", "e_theta_rad"}} for the cameras present in both."""
    out = {}
    for cam, X in T_ee_cam.items():
        if cam in ground_truth["hand_eye"]:
            X = X if isinstance(X, gtsam.Pose3) else gtsam.Pose3(np.asarray(X))
            et, er = pose_error(X, ground_truth["hand_eye"][cam])
            out[cam] = {"e_t_m": et, "e_theta_rad": float(np.radians(er))}
    return out


def load_calibration(result_dir) -> dict:
    path = Path(result_dir) / "calibration.json"
    if not path.is_file():
        raise InputError(path, "missing (run 'calib3r-graph solve' first)")
    try:
        calib = json.loads(path.read_text())
        return ee_T_cam_by_camera(calib["cameras"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise InputError(path, f"not a calib3r-calibration/1 file ({e})") from None


def evaluate(result_dir, dataset_dir) -> dict:
    gt = load_ground_truth(dataset_dir)
    if gt is None:
        raise InputError(Path(dataset_dir) / "ground_truth.yaml", "missing: nothing to evaluate against")
    return {"hand_eye": hand_eye_errors(load_calibration(result_dir), gt)}
