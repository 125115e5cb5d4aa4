"""Reading and writing ``calib3r-dataset/1`` (dataset.yaml, robot_poses.csv, images, depth).

Every check happens here, at the boundary: a violation raises :class:`InputError`
naming the file, the row or key, and what is wrong. Translations are converted to
metres on load, so nothing downstream sees ``unit``.
"""

import csv
import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import gtsam
import numpy as np
import yaml

from calib3r_graph.errors import InputError

log = logging.getLogger(__name__)

FORMAT = "calib3r-dataset/1"
# COLMAP's names and parameter orders: fx fy cx cy, then OPENCV's k1 k2 p1 p2, then FULL_OPENCV's
# k3 k4 k5 k6 (OpenCV's rational model; k4-k6 zero is its 5-coefficient plumb_bob)
CAMERA_MODELS = {"PINHOLE": 4, "OPENCV": 8, "FULL_OPENCV": 12}
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
ROBOT_COLUMNS = ["frame", "x", "y", "z", "qx", "qy", "qz", "qw"]
UNIT_TO_METRES = {"m": 1.0, "mm": 1e-3}
# Industrial arms reach at most a few metres; a flange farther than this from the base
# means the translations are in a smaller unit than declared.
MAX_PLAUSIBLE_REACH_M = 20.0


@dataclass(frozen=True)
class Camera:
    name: str
    model: str
    width: int
    height: int
    params: tuple
    depth_scale: float | None = None
    # 1-sigma of fx, fy, cx, cy (px), optional: the intrinsics' own uncertainty, which solve
    # propagates into the total covariance (solver/camera_model.py); None = not stated
    params_sigma: tuple | None = None

    @property
    def K(self) -> np.ndarray:
        fx, fy, cx, cy = self.params[:4]
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """OpenCV's distortion coefficients: [k1, k2, p1, p2] (zeros for PINHOLE); FULL_OPENCV's
        [k1, k2, p1, p2, k3], or all eight with k4, k5, k6 when the rational terms are set."""
        if self.model == "FULL_OPENCV":
            return np.array(self.params[4:12] if any(self.params[9:12]) else self.params[4:9])
        return np.array(self.params[4:8] if self.model == "OPENCV" else [0.0] * 4)


def opencv_camera(name: str, size, K, dist, depth_scale=None, params_sigma=None) -> Camera:
    """A Camera from OpenCV's K and distortion coefficients (none, 4, 5 or 8): OPENCV up to k1, k2,
    p1, p2, FULL_OPENCV (zeros for the unset k3-k6) beyond."""
    d = np.zeros(4) if dist is None else np.ravel(dist).astype(float)
    model = "FULL_OPENCV" if d.size > 4 and np.any(d[4:] != 0) else "OPENCV"
    n = CAMERA_MODELS[model] - 4
    d = np.r_[d, np.zeros(max(0, n - d.size))][:n]
    return Camera(name, model, int(size[0]), int(size[1]),
                  tuple(float(x) for x in (K[0, 0], K[1, 1], K[0, 2], K[1, 2], *d)), depth_scale,
                  None if params_sigma is None else tuple(float(x) for x in params_sigma))


@dataclass
class Dataset:
    root: Path
    cameras: dict  # name -> Camera, in dataset.yaml order
    base_T_ee: dict  # frame id -> gtsam.Pose3 (metres)
    pattern: dict | None = None
    robot_unit: str = "m"
    meta: dict = field(default_factory=dict)  # the parsed dataset.yaml

    @property
    def frames(self) -> list:
        return list(self.base_T_ee)

    def image_path(self, camera: str, frame: str) -> Path | None:
        for suffix in IMAGE_SUFFIXES:
            p = self.root / "images" / camera / f"{frame}{suffix}"
            if p.is_file():
                return p
        return None

    def depth_path(self, camera: str, frame: str) -> Path | None:
        p = self.root / "depth" / camera / f"{frame}.png"
        return p if p.is_file() else None

    def image_frames(self, camera: str) -> list:
        d = self.root / "images" / camera
        if not d.is_dir():
            return []
        return sorted(p.stem for p in d.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)

    def has_depth(self) -> bool:
        return any(self.depth_path(c, f) for c in self.cameras for f in self.frames[:3])


def _require(mapping, key, path, where):
    if not isinstance(mapping, dict) or key not in mapping:
        raise InputError(path, f"missing key '{key}'", where)
    return mapping[key]


def _parse_camera(entry, path, index) -> Camera:
    where = f"cameras[{index}]"
    if not isinstance(entry, dict):
        raise InputError(path, "each camera must be a mapping", where)
    name = str(_require(entry, "name", path, where))
    where = f"cameras[{index}] ({name})"
    model = str(_require(entry, "model", path, where))
    if model not in CAMERA_MODELS:
        raise InputError(path, f"unknown camera model '{model}' (expected one of {sorted(CAMERA_MODELS)})", where)
    try:
        width, height = int(_require(entry, "width", path, where)), int(_require(entry, "height", path, where))
        params = tuple(float(p) for p in _require(entry, "params", path, where))
    except (TypeError, ValueError) as e:
        raise InputError(path, f"width, height and params must be numbers ({e})", where) from None
    if len(params) != CAMERA_MODELS[model]:
        raise InputError(path, f"{model} needs {CAMERA_MODELS[model]} params, got {len(params)}", where)
    if width <= 0 or height <= 0 or params[0] <= 0 or params[1] <= 0 or not all(map(math.isfinite, params)):
        raise InputError(path, "width, height, fx and fy must be positive and params finite", where)
    depth_scale = entry.get("depth_scale")
    if depth_scale is not None:
        if not isinstance(depth_scale, (int, float)) or not depth_scale > 0:
            raise InputError(path, "depth_scale must be a positive number (metres per depth unit)", where)
        depth_scale = float(depth_scale)
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", name):
        raise InputError(path, f"camera name '{name}' must be letters, digits, '_', '.' or '-'", where)
    params_sigma = entry.get("params_sigma")
    if params_sigma is not None:
        try:
            params_sigma = tuple(float(x) for x in params_sigma)
        except (TypeError, ValueError):
            params_sigma = ()
        if len(params_sigma) != 4 or not all(math.isfinite(x) and x >= 0 for x in params_sigma):
            raise InputError(path, "params_sigma must be four numbers >= 0: the 1-sigma of fx, fy, cx, cy in px",
                             where)
    return Camera(name, model, width, height, params, depth_scale, params_sigma)


def load_dataset(root, skip_missing: bool = False) -> Dataset:
    """Load and validate ``root/dataset.yaml`` and the robot poses it names."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "no such dataset directory")
    path = root / "dataset.yaml"
    if not path.is_file():
        raise InputError(path, "missing (every dataset needs a dataset.yaml)")
    try:
        meta = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise InputError(path, f"not valid YAML ({first})") from None
    if not isinstance(meta, dict):
        raise InputError(path, "must be a YAML mapping")
    try:
        return _interpret(root, path, meta, skip_missing)
    except (TypeError, ValueError, AttributeError) as e:  # a value of the wrong type the checks did not name
        raise InputError(path, f"invalid content ({type(e).__name__}: {e})") from None


def _interpret(root: Path, path: Path, meta: dict, skip_missing: bool) -> Dataset:
    fmt = _require(meta, "format", path, None)
    if not isinstance(meta.get("robot"), dict):
        raise InputError(path, "must be a mapping with poses and unit", "robot")
    if fmt != FORMAT:
        raise InputError(path, f"unknown format '{fmt}' (this version reads '{FORMAT}')", "format")
    robot = _require(meta, "robot", path, None)
    poses_name = _require(robot, "poses", path, "robot")
    unit = str(robot.get("unit", "m"))
    if unit not in UNIT_TO_METRES:
        raise InputError(path, f"unknown unit '{unit}' (expected m or mm)", "robot.unit")
    cams = _require(meta, "cameras", path, None)
    if not isinstance(cams, list) or not cams:
        raise InputError(path, "must list at least one camera", "cameras")
    cameras = {}
    for i, entry in enumerate(cams):
        cam = _parse_camera(entry, path, i)
        if cam.name in cameras:
            raise InputError(path, f"camera name '{cam.name}' appears twice", f"cameras[{i}]")
        cameras[cam.name] = cam
    pattern = meta.get("pattern")
    if pattern is not None:
        _validate_pattern(pattern, path)
    base_T_ee = read_robot_poses(root / str(poses_name), unit)
    ds = Dataset(root, cameras, base_T_ee, pattern, unit, meta)
    _check_frames_have_poses(ds, skip_missing)
    _check_image_sizes(ds)
    return ds


def _validate_pattern(pattern, path):
    if not isinstance(pattern, dict):
        raise InputError(path, "must be a mapping with type, inner_corners and square_size", "pattern")
    if pattern.get("type") in ("charuco", "circles", "asymmetric_circles"):  # see calib3r_graph/io/boards.py
        from calib3r_graph.io.boards import from_pattern

        from_pattern(pattern, path)
        return
    if pattern.get("type") != "checkerboard":
        raise InputError(path, f"unsupported pattern type '{pattern.get('type')}'", "pattern.type")
    corners = pattern.get("inner_corners")
    if not (isinstance(corners, list) and len(corners) == 2 and all(isinstance(c, int) and c >= 2 for c in corners)):
        raise InputError(path, "inner_corners must be [columns, rows], integers >= 2", "pattern.inner_corners")
    size = pattern.get("square_size")
    if not isinstance(size, (int, float)) or not size > 0:
        raise InputError(path, "square_size must be a positive number of metres", "pattern.square_size")


def read_robot_poses(path: Path, unit: str = "m", role: str = "named by dataset.yaml robot.poses") -> dict:
    """``robot_poses.csv`` (or a file in its format) -> {frame: base_T_ee Pose3 in metres}, strictly validated."""
    if not path.is_file():
        raise InputError(path, f"missing ({role})")
    try:
        # utf-8-sig: files written by Windows tools start with a byte-order mark; CRLF line ends and
        # spaces after the commas are accepted too
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(path, "not a text file") from None
    rows = list(csv.reader(text.splitlines(), skipinitialspace=True))
    if not rows or [c.strip() for c in rows[0]] != ROBOT_COLUMNS:
        raise InputError(path, f"header must be '{','.join(ROBOT_COLUMNS)}'", "row 1")
    scale = UNIT_TO_METRES[unit]
    poses = {}
    for line_no, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        where = f"row {line_no}"
        if len(row) != len(ROBOT_COLUMNS):
            raise InputError(path, f"expected {len(ROBOT_COLUMNS)} columns, got {len(row)}", where)
        frame = row[0].strip()
        where = f"row {line_no} (frame {frame})"
        if not frame:
            raise InputError(path, "empty frame id", where)
        if frame in poses:
            raise InputError(path, "duplicated frame", where)
        try:
            x, y, z, qx, qy, qz, qw = (float(c) for c in row[1:])
        except ValueError:
            raise InputError(path, "pose values must be numbers", where) from None
        values = (x, y, z, qx, qy, qz, qw)
        if not all(math.isfinite(v) for v in values):
            raise InputError(path, "NaN or Inf in the pose", where)
        norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        if abs(norm - 1.0) > 1e-3:
            raise InputError(path, f"quaternion is not unit (norm {norm:.6g})", where)
        rot = gtsam.Rot3.Quaternion(qw / norm, qx / norm, qy / norm, qz / norm)
        poses[frame] = gtsam.Pose3(rot, np.array([x, y, z]) * scale)
    if not poses:
        raise InputError(path, "no poses")
    reach = max(np.linalg.norm(p.translation()) for p in poses.values())
    if reach > MAX_PLAUSIBLE_REACH_M:
        raise InputError(path, f"flange is {reach:.0f} m from the base: translations look like millimetres "
                               f"declared as '{unit}' (set robot.unit: mm in dataset.yaml)")
    spread = np.ptp(np.array([p.translation() for p in poses.values()]), axis=0).max() if len(poses) > 1 else 1.0
    if len(poses) > 2 and spread < 1e-3 and unit == "mm":
        raise InputError(path, "the flange moves less than 1 mm over all frames: translations look like "
                               "metres declared as 'mm' (set robot.unit: m in dataset.yaml)")
    return poses


def _check_frames_have_poses(ds: Dataset, skip_missing: bool):
    """Every frame with images must have a robot pose (or be skipped with a warning)."""
    for cam in ds.cameras:
        for frame in ds.image_frames(cam):
            if frame not in ds.base_T_ee:
                path = ds.image_path(cam, frame)
                if not skip_missing:
                    raise InputError(path, f"frame {frame} has no row in robot_poses.csv "
                                           "(use --skip-missing to drop such frames)")
                log.warning("%s: frame %s has no robot pose; skipped", path, frame)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of a PNG or JPEG from its header alone (no decoding, no image library)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(26)
            if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
                return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
            if head[:2] == b"\xff\xd8":
                fh.seek(2)
                while True:
                    marker = fh.read(2)
                    if len(marker) < 2 or marker[0] != 0xFF:
                        break
                    while marker[1] == 0xFF:  # fill bytes
                        marker = marker[1:] + fh.read(1)
                    kind = marker[1]
                    if kind in (0xD8, 0x01) or 0xD0 <= kind <= 0xD7:  # markers without a length
                        continue
                    length = int.from_bytes(fh.read(2), "big")
                    if 0xC0 <= kind <= 0xCF and kind not in (0xC4, 0xC8, 0xCC):  # start of frame
                        sof = fh.read(5)
                        if len(sof) == 5:
                            return int.from_bytes(sof[3:5], "big"), int.from_bytes(sof[1:3], "big")
                        break
                    if length < 2:
                        break
                    fh.seek(length - 2, 1)
    except OSError as e:
        raise InputError(path, f"cannot be read ({e.strerror or e})") from None
    raise InputError(path, "not a readable PNG or JPEG image")


def _check_image_sizes(ds: Dataset):
    """Every image and depth map of the dataset's frames has its camera's size in dataset.yaml."""
    for name, cam in ds.cameras.items():
        for frame in ds.frames:
            for kind, path in (("image", ds.image_path(name, frame)), ("depth map", ds.depth_path(name, frame))):
                if path is None:
                    continue
                w, h = image_size(path)
                if (w, h) != (cam.width, cam.height):
                    raise InputError(path, f"{kind} is {w}x{h} pixels but dataset.yaml gives camera {name} "
                                           f"{cam.width}x{cam.height} (width x height); resize it back or fix "
                                           "the camera's width, height and intrinsics")


def pose_to_row(frame: str, pose: gtsam.Pose3, scale: float = 1.0) -> list:
    q = pose.rotation().toQuaternion()
    t = pose.translation() * scale
    return [frame, *(f"{v:.9f}" for v in t), *(f"{v:.12f}" for v in (q.x(), q.y(), q.z(), q.w()))]


def write_robot_poses(path: Path, base_T_ee: dict, unit: str = "m"):
    from calib3r_graph.io.output import atomic_write_text

    scale = 1.0 / UNIT_TO_METRES[unit]
    lines = [",".join(ROBOT_COLUMNS)] + [",".join(pose_to_row(f, p, scale)) for f, p in base_T_ee.items()]
    atomic_write_text(path, "\n".join(lines) + "\n")


def camera_to_yaml(cam: Camera) -> dict:
    d = {"name": cam.name, "model": cam.model, "width": cam.width, "height": cam.height,
         "params": [float(p) for p in cam.params]}
    if cam.depth_scale is not None:
        d["depth_scale"] = cam.depth_scale
    if cam.params_sigma is not None:
        d["params_sigma"] = [float(x) for x in cam.params_sigma]
    return d


def write_dataset_yaml(root: Path, cameras, unit="m", pattern=None, poses_name="robot_poses.csv", extra=None):
    from calib3r_graph.io.output import atomic_write_text

    meta = {"format": FORMAT, "robot": {"poses": poses_name, "unit": unit},
            "cameras": [camera_to_yaml(c) for c in cameras]}
    if pattern:
        meta["pattern"] = pattern
    meta.update(extra or {})
    atomic_write_text(Path(root) / "dataset.yaml", yaml.safe_dump(meta, sort_keys=False))


def pose_from_dict(d) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Quaternion(d["qw"], d["qx"], d["qy"], d["qz"]), np.array([d["x"], d["y"], d["z"]]))


def subset_dataset(ds, frames):
    """The dataset restricted to the given frames (robot poses of other frames dropped)."""
    import dataclasses

    frames = set(frames)
    return dataclasses.replace(ds, base_T_ee={f: p for f, p in ds.base_T_ee.items() if f in frames})


def ee_T_cam_by_camera(cameras: dict) -> dict:
    """{camera: Pose3} from the ``{camera: {"T_ee_cam": 4x4, ...}}`` of a calibration.json or a
    comparison.json method."""
    return {c: gtsam.Pose3(np.asarray(v["T_ee_cam"], dtype=float)) for c, v in cameras.items()}


def pose_to_dict(pose: gtsam.Pose3) -> dict:
    q = pose.rotation().toQuaternion()
    t = pose.translation()
    return {"x": float(t[0]), "y": float(t[1]), "z": float(t[2]),
            "qx": float(q.x()), "qy": float(q.y()), "qz": float(q.z()), "qw": float(q.w())}


def load_ground_truth(root) -> dict | None:
    """``ground_truth.yaml`` -> {"hand_eye": {camera: ee_T_cam Pose3}, ...}; None if absent."""
    path = Path(root) / "ground_truth.yaml"
    if not path.is_file():
        return None
    try:
        gt = yaml.safe_load(path.read_text())
        gt["hand_eye"] = {c: pose_from_dict(d) for c, d in gt["hand_eye"].items()}
    except (yaml.YAMLError, KeyError, TypeError) as e:
        raise InputError(path, f"invalid ground truth ({e})") from None
    return gt
