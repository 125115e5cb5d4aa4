"""Camera intrinsics from the files calibration tools write, as the OPENCV model (fx, fy, cx,
cy, k1, k2, p1, p2) in OpenCV's pixel-centre convention.

* ROS ``camera_info`` YAML (camera_calibration_parsers: ``image_width``, ``camera_matrix: {rows,
  cols, data}``, ``distortion_model``, ``distortion_coefficients``), or a CameraInfo message as
  ``ros2 topic echo`` prints it (``width``, ``k``, ``d``);
* OpenCV FileStorage YAML or XML (``camera_matrix``, ``distortion_coefficients``, and
  ``image_width``/``image_height`` when present), as OpenCV's calibration sample writes it;
* a Kalibr camchain (``cam0: {camera_model: pinhole, intrinsics: [fu, fv, pu, pv],
  distortion_model: radtan, distortion_coeffs, resolution}``), one entry per camera.

Distortion beyond k1, k2, p1, p2 (k3, the rational model's k4-k6) is dropped with a warning
when it moves no pixel of the image by more than 1 px, and is an error otherwise; fisheye
(equidistant) models are an error.
"""

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from calib3r_graph.errors import InputError

log = logging.getLogger(__name__)
RADTAN = ("plumb_bob", "radtan", "rational_polynomial", "opencv", "")
NO_DISTORTION = ("none", "pinhole")


@dataclass
class Intrinsics:
    K: np.ndarray  # 3x3
    dist: np.ndarray  # [k1, k2, p1, p2]
    width: int | None
    height: int | None
    source: str

    @property
    def params(self) -> tuple:
        return tuple(float(x) for x in (self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2], *self.dist))


def opencv_distortion(coeffs, model, K, size, path) -> np.ndarray:
    model = str(model or "").lower()
    if model in ("equidistant", "fisheye", "kannala_brandt", "equi"):
        raise InputError(path, f"distortion model '{model}' (fisheye) is not supported: calib3r-graph uses OpenCV's "
                               "k1, k2, p1, p2 model; recalibrate with plumb_bob/radtan")
    if model not in RADTAN + NO_DISTORTION:
        raise InputError(path, f"unknown distortion model '{model}' (expected plumb_bob, radtan or "
                               "rational_polynomial)")
    d = np.zeros(4) if coeffs is None else np.asarray(coeffs, dtype=float).ravel()
    if not np.all(np.isfinite(d)):
        raise InputError(path, "NaN or Inf in the distortion coefficients")
    extra, d = d[4:], np.r_[d[:4], np.zeros(max(0, 4 - d.size))][:4]
    if np.any(extra != 0):
        # How far the dropped terms move the image's corner (normalised radius r): k3 r^7 f for k3,
        # the rational denominator (k4 r^2 + k5 r^4 + k6 r^6) similarly.
        if size:
            w, h = size
            r = max(np.hypot((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]) for u in (0, w) for v in (0, h))
        else:
            r = 1.0
        powers = [6, 2, 4, 6][:len(extra)]
        shift = float(K[0, 0] * r * sum(abs(e) * r ** p for e, p in zip(extra, powers)))
        if shift > 1.0:
            raise InputError(path, f"distortion terms beyond k1, k2, p1, p2 ({', '.join(f'{e:g}' for e in extra)}) "
                                   f"move the image corners by up to {shift:.1f} px, and calib3r-graph's OPENCV model "
                                   "has only k1, k2, p1, p2: recalibrate with k3 fixed at 0")
        log.warning("%s: distortion terms beyond k1, k2, p1, p2 dropped (they move no pixel by more than %.2f px)",
                    path, shift)
    return d


def _camera_matrix(values, path, key) -> np.ndarray:
    try:
        K = np.asarray(values, dtype=float).reshape(3, 3)
    except (TypeError, ValueError):
        raise InputError(path, "must hold 9 numbers (3x3)", key) from None
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1])):
        raise InputError(path, "not a camera matrix (fx, fy > 0, last row 0 0 1)", key)
    return K


def _data(node, path, key):
    if isinstance(node, dict):
        if "data" not in node:
            raise InputError(path, "expected a mapping with 'data'", key)
        return node["data"]
    return node


def _from_ros_yaml(meta: dict, path) -> Intrinsics:
    if "camera_matrix" in meta:  # camera_calibration_parsers
        K = _camera_matrix(_data(meta["camera_matrix"], path, "camera_matrix"), path, "camera_matrix")
        size = (int(meta["image_width"]), int(meta["image_height"])) if "image_width" in meta else None
        coeffs = _data(meta.get("distortion_coefficients"), path, "distortion_coefficients")
        model = meta.get("distortion_model", "plumb_bob")
    else:  # a CameraInfo message
        K = _camera_matrix(meta.get("k", meta.get("K")), path, "k")
        size = (int(meta["width"]), int(meta["height"])) if meta.get("width") else None
        coeffs, model = meta.get("d", meta.get("D")), meta.get("distortion_model", "plumb_bob")
    return Intrinsics(K, opencv_distortion(coeffs, model, K, size, path), *(size or (None, None)),
                      f"ROS camera_info {path}")


def _from_kalibr(meta: dict, path) -> list:
    out = []
    for name in sorted((k for k in meta if str(k).startswith("cam")), key=lambda k: int("0" + str(k)[3:])):
        cam = meta[name]
        if not isinstance(cam, dict) or "intrinsics" not in cam:
            raise InputError(path, "a Kalibr camchain entry needs intrinsics", name)
        if str(cam.get("camera_model", "pinhole")).lower() != "pinhole":
            raise InputError(path, f"camera model '{cam.get('camera_model')}' is not supported (pinhole only)", name)
        fx, fy, cx, cy = (float(v) for v in cam["intrinsics"])
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        size = tuple(int(v) for v in cam["resolution"]) if cam.get("resolution") else None
        dist = opencv_distortion(cam.get("distortion_coeffs"), cam.get("distortion_model", "radtan"), K, size, path)
        out.append(Intrinsics(K, dist, *(size or (None, None)), f"Kalibr camchain {path} ({name})"))
    return out


def _from_filestorage(path) -> Intrinsics:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        if not fs.isOpened():
            raise InputError(path, "not an OpenCV FileStorage YAML/XML file")

        def node(*names):
            for n in names:
                nd = fs.getNode(n)
                if not nd.empty():
                    return nd
            return None

        k = node("camera_matrix", "cameraMatrix", "K", "intrinsic_matrix")
        if k is None:
            raise InputError(path, "no camera_matrix in it (ROS camera_info, OpenCV FileStorage or Kalibr camchain "
                                   "expected)")
        K = _camera_matrix(k.mat(), path, "camera_matrix")
        d = node("distortion_coefficients", "dist_coeffs", "distCoeffs", "D")
        w, h = node("image_width", "imageWidth"), node("image_height", "imageHeight")
        size = (int(w.real()), int(h.real())) if w is not None and h is not None else None
        dist = opencv_distortion(None if d is None else d.mat(), "plumb_bob", K, size, path)
    finally:
        fs.release()
    return Intrinsics(K, dist, *(size or (None, None)), f"OpenCV FileStorage {path}")


def read_intrinsics(path) -> list:
    """[Intrinsics] of a file: one camera, or several for a Kalibr camchain."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such intrinsics file")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (UnicodeDecodeError, OSError):
        raise InputError(path, "not a text file") from None
    if path.suffix.lower() == ".xml" or text.lstrip().startswith("%YAML") or "!!opencv-matrix" in text:
        return [_from_filestorage(path)]
    try:
        meta = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise InputError(path, f"not valid YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(meta, dict):
        raise InputError(path, "expected a YAML mapping (ROS camera_info, OpenCV FileStorage or Kalibr camchain)")
    try:
        if "camera_matrix" in meta or "k" in meta or "K" in meta:
            return [_from_ros_yaml(meta, path)]
        if any(str(k).startswith("cam") and isinstance(v, dict) and "intrinsics" in v for k, v in meta.items()):
            return _from_kalibr(meta, path)
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(path, f"invalid intrinsics ({type(e).__name__}: {e})") from None
    raise InputError(path, "not a ROS camera_info, OpenCV FileStorage or Kalibr camchain file (no camera_matrix, "
                           "k or cam0.intrinsics)")
