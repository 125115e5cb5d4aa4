"""Camera intrinsics from the files calibration tools write, as OpenCV's camera matrix and
distortion coefficients, in OpenCV's pixel-centre convention.

* ROS ``camera_info`` YAML (camera_calibration_parsers: ``image_width``, ``camera_matrix: {rows,
  cols, data}``, ``distortion_model``, ``distortion_coefficients``), or a CameraInfo message as
  ``ros2 topic echo`` prints it (``width``, ``k``, ``d``);
* OpenCV FileStorage YAML or XML (``camera_matrix``, ``distortion_coefficients``, and
  ``image_width``/``image_height`` when present), as OpenCV's calibration sample writes it;
* a Kalibr camchain (``cam0: {camera_model: pinhole, intrinsics: [fu, fv, pu, pv],
  distortion_model: radtan, distortion_coeffs, resolution}``), one entry per camera;
* ViSP's ``camera.xml`` (vpXmlParserCamera: ``<root><camera><name/><image_width/><image_height/>
  <model><type/><px/><py/><u0/><v0/>[<kud/><kdu/>]</model></camera></root>``). ViSP's model with
  distortion maps the undistorted normalised point (x, y) to ``u = u0 + px x (1 + kud r²)``,
  ``v = v0 + py y (1 + kud r²)``: OpenCV's k1 = kud, the other coefficients 0 (``kdu`` is the
  inverse map's and is not needed). Several ``<camera>`` entries: the one named by
  ``--camera-name``, else the only one, else the only one of the images' size;
* a NumPy ``.npz`` with ``K`` (or ``camera_matrix``, ``mtx``) and ``dist`` (or ``D``,
  ``dist_coeffs``, ``distortion_coefficients``), optionally ``image_size`` (width, height).

The whole OpenCV lens model is kept: k1, k2, p1, p2 (4 coefficients), with k3 (5: ROS plumb_bob,
a RealSense's factory model), or rational with k4, k5, k6 (8). Thin-prism and tilt terms and
fisheye (equidistant) models are an error. Any file that is none of these is a one-line error
that lists the accepted formats.
"""

import xml.etree.ElementTree as ET
import zipfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from calib3r_graph.errors import InputError

RADTAN = ("plumb_bob", "radtan", "rational_polynomial", "opencv", "full_opencv", "")
NO_DISTORTION = ("none", "pinhole")
ACCEPTED = ("accepted: ROS camera_info YAML, OpenCV FileStorage YAML/XML, Kalibr camchain YAML, ViSP camera.xml, "
            ".npz with K and dist")
NPZ_K, NPZ_DIST = ("K", "camera_matrix", "mtx", "cameraMatrix"), ("dist", "D", "dist_coeffs",
                                                                 "distortion_coefficients", "distCoeffs")


@dataclass
class Intrinsics:
    K: np.ndarray  # 3x3
    dist: np.ndarray  # as OpenCV takes it: [k1, k2, p1, p2], [.., k3] or [.., k3, k4, k5, k6]
    width: int | None
    height: int | None
    source: str

    @property
    def params(self) -> tuple:
        return tuple(float(x) for x in (self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2], *self.dist))


def opencv_distortion(coeffs, model, path) -> np.ndarray:
    """The coefficients as OpenCV takes them, trailing zeros dropped: [k1, k2, p1, p2], [k1, k2, p1, p2,
    k3] or [k1, k2, p1, p2, k3, k4, k5, k6]."""
    model = str(model or "").lower()
    if model in ("equidistant", "fisheye", "kannala_brandt", "equi"):
        raise InputError(path, f"distortion model '{model}' (fisheye) is not supported: calib3r-graph uses OpenCV's "
                               "k1, k2, p1, p2[, k3[, k4, k5, k6]] model; recalibrate with plumb_bob/radtan")
    if model not in RADTAN + NO_DISTORTION:
        raise InputError(path, f"unknown distortion model '{model}' (expected plumb_bob, radtan or "
                               "rational_polynomial)")
    d = np.zeros(4) if coeffs is None else np.asarray(coeffs, dtype=float).ravel()
    if not np.all(np.isfinite(d)):
        raise InputError(path, "NaN or Inf in the distortion coefficients")
    if np.any(d[8:] != 0):
        raise InputError(path, f"{d.size} distortion coefficients with thin-prism or tilt terms (s1-s4, tx, ty) "
                               "set: calib3r-graph takes OpenCV's k1, k2, p1, p2, k3, k4, k5, k6")
    d = np.r_[d[:8], np.zeros(max(0, 4 - d.size))]
    return d[:8] if np.any(d[5:8] != 0) else d[:5] if d.size > 4 and d[4] != 0 else d[:4]


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
    return Intrinsics(K, opencv_distortion(coeffs, model, path), *(size or (None, None)),
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
        dist = opencv_distortion(cam.get("distortion_coeffs"), cam.get("distortion_model", "radtan"), path)
        out.append(Intrinsics(K, dist, *(size or (None, None)), f"Kalibr camchain {path} ({name})"))
    return out


def _from_filestorage(path) -> Intrinsics:
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):  # OpenCV raises on a file it cannot parse
        raise InputError(path, f"not a readable OpenCV FileStorage file ({ACCEPTED})") from None
    try:
        if not fs.isOpened():
            raise InputError(path, f"not an OpenCV FileStorage YAML/XML file ({ACCEPTED})")

        def node(*names):
            for n in names:
                nd = fs.getNode(n)
                if not nd.empty():
                    return nd
            return None

        k = node("camera_matrix", "cameraMatrix", "K", "intrinsic_matrix")
        if k is None:
            raise InputError(path, f"no camera_matrix in it ({ACCEPTED})")
        K = _camera_matrix(k.mat(), path, "camera_matrix")
        d = node("distortion_coefficients", "dist_coeffs", "distCoeffs", "D")
        w, h = node("image_width", "imageWidth"), node("image_height", "imageHeight")
        size = (int(w.real()), int(h.real())) if w is not None and h is not None else None
        dist = opencv_distortion(None if d is None else d.mat(), "plumb_bob", path)
    finally:
        fs.release()
    return Intrinsics(K, dist, *(size or (None, None)), f"OpenCV FileStorage {path}")


def _from_visp(path, root, camera_name=None, size=None) -> Intrinsics:
    """One camera of a ViSP camera.xml (see the module's docstring for the model)."""
    cams = []
    for node in root.findall("camera"):
        w, h = node.findtext("image_width"), node.findtext("image_height")
        models = {(m.findtext("type") or "").strip(): m for m in node.findall("model")}
        cams.append(((node.findtext("name") or "").strip(), (int(w), int(h)) if w and h else None, models))
    names = ", ".join(f"'{c[0]}'" for c in cams)
    pick = [c for c in cams if camera_name is None or c[0] == camera_name]
    which = f" named '{camera_name}'" if camera_name is not None else ""
    if len(pick) > 1 and size is not None:
        pick = [c for c in pick if c[1] == tuple(size)]
        which += f" for {size[0]}x{size[1]} images"
    if len(pick) != 1:
        hint = "" if camera_name is not None and not pick else ": name one with --camera-name"
        raise InputError(path, f"{len(pick) or 'no'} ViSP cameras{which} among the {len(cams)} in it "
                               f"({names or 'none'}){hint}")
    name, wh, models = pick[0]
    model = models.get("perspectiveProjWithDistortion", models.get("perspectiveProjWithoutDistortion"))
    if model is None:
        raise InputError(path, f"camera '{name}' has no perspectiveProjWithDistortion or "
                               f"perspectiveProjWithoutDistortion model (found {', '.join(models) or 'none'})")
    try:
        px, py, u0, v0 = (float(model.findtext(k)) for k in ("px", "py", "u0", "v0"))
        kud = float(model.findtext("kud")) if "perspectiveProjWithDistortion" in models else 0.0
    except (TypeError, ValueError):
        raise InputError(path, "a ViSP model needs numbers px, py, u0, v0 (and kud with distortion)",
                         f"camera '{name}'") from None
    K = _camera_matrix([px, 0, u0, 0, py, v0, 0, 0, 1], path, f"camera '{name}'")
    return Intrinsics(K, opencv_distortion([kud, 0, 0, 0], "plumb_bob", path), *(wh or (None, None)),
                      f"ViSP camera.xml {path} ('{name}')")


def _from_xml(path, camera_name=None, size=None) -> Intrinsics:
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as e:
        raise InputError(path, f"not valid XML ({e}; {ACCEPTED})") from None
    if root.tag == "opencv_storage":
        return _from_filestorage(path)
    if root.find("camera") is not None:
        return _from_visp(path, root, camera_name, size)
    raise InputError(path, f"XML with root <{root.tag}>: neither OpenCV FileStorage nor ViSP camera.xml ({ACCEPTED})")


def _from_npz(path) -> Intrinsics:
    try:
        z = np.load(path, allow_pickle=False)
        arrays = {k: z[k] for k in z.files}
    except (ValueError, OSError, zipfile.BadZipFile, EOFError) as e:
        raise InputError(path, f"not a readable .npz ({type(e).__name__}; {ACCEPTED})") from None
    k = next((n for n in NPZ_K if n in arrays), None)
    d = next((n for n in NPZ_DIST if n in arrays), None)
    if k is None or d is None:
        raise InputError(path, f"an .npz of intrinsics needs {' or '.join(NPZ_K[:3])} and {' or '.join(NPZ_DIST[:4])}; "
                               f"it holds {', '.join(arrays) or 'nothing'} ({ACCEPTED})")
    K = _camera_matrix(arrays[k], path, k)
    size = arrays.get("image_size", arrays.get("size"))
    size = tuple(int(v) for v in np.ravel(size)[:2]) if size is not None else None
    return Intrinsics(K, opencv_distortion(arrays[d], "plumb_bob", path), *(size or (None, None)), f"NumPy {path}")


def read_intrinsics(path, camera_name=None, size=None) -> list:
    """[Intrinsics] of a file: one camera, or several for a Kalibr camchain. ``camera_name`` and
    ``size`` (the images' width, height) pick one camera of a ViSP file that holds several."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such intrinsics file")
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise InputError(path, f"cannot be read ({e.strerror or e})") from None
    if path.suffix.lower() == ".npz" or raw[:4] == b"PK\x03\x04":
        return [_from_npz(path)]
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(path, f"not a text file ({ACCEPTED})") from None
    if path.suffix.lower() == ".xml" or text.lstrip().startswith("<"):
        return [_from_xml(path, camera_name, size)]
    if text.lstrip().startswith("%YAML") or "!!opencv-matrix" in text:
        return [_from_filestorage(path)]
    try:
        meta = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise InputError(path, f"not valid YAML ({str(e).splitlines()[0]}; {ACCEPTED})") from None
    if not isinstance(meta, dict):
        raise InputError(path, f"expected a YAML mapping ({ACCEPTED})")
    try:
        if "camera_matrix" in meta or "k" in meta or "K" in meta:
            return [_from_ros_yaml(meta, path)]
        if any(str(k).startswith("cam") and isinstance(v, dict) and "intrinsics" in v for k, v in meta.items()):
            return _from_kalibr(meta, path)
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(path, f"invalid intrinsics ({type(e).__name__}: {e})") from None
    raise InputError(path, f"no camera_matrix, k or cam0.intrinsics in it: not a ROS camera_info, OpenCV FileStorage "
                           f"or Kalibr camchain file ({ACCEPTED})")
