"""Robot pose files: the formats controllers and tools write, read into 4x4 matrices.

Formats (``--pose-format``), translation first, in the file's unit:

* ``matrix``: a 4x4 row-major matrix (16 numbers; or four lines of four);
* ``xyz-quat-xyzw`` and ``xyz-quat-wxyz``: x y z and a unit quaternion;
* ``xyz-rotvec``: x y z and a rotation vector in radians (UR controllers' ``p[x,y,z,rx,ry,rz]``);
* ``xyz-euler:ORDER:deg|rad``: x y z a b c. ORDER is three axes about which the angles turn in
  the order written, each about the axes as already turned (R = R_o1(a)·R_o2(b)·R_o3(c)):
  KUKA's A, B, C is ``zyx``. ``fixed-ORDER`` turns about the base's fixed axes instead
  (R = R_o3(c)·R_o2(b)·R_o1(a)): ROS roll, pitch, yaw and Fanuc's W, P, R are ``fixed-xyz``;
* ``visp``: ViSP's vpPoseVector, t and θu (as ``xyz-rotvec``), also its per-frame YAML.

Where the poses come from (``--poses``):

* one file, one pose per line (a leading extra column is the frame number; ``#`` comments and
  a header line are skipped), or a JSON/YAML list or ``{frame: pose}`` mapping, or an .npy of
  shape (N, 4, 4) or (N, k);
* a folder or a glob: one file per frame (.txt, .csv, .npy, .json, .yaml), numbered by the last
  number in its name.

Each pose is returned as it is written (direction and unit untouched): the importer checks
both against the images.
"""

import glob
import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from calib3r_graph.errors import InputError

FORMAT_HELP = "matrix, xyz-quat-xyzw, xyz-quat-wxyz, xyz-rotvec, xyz-euler:ORDER:deg|rad (e.g. xyz-euler:zyx:deg), visp"
PER_FRAME_SUFFIXES = (".txt", ".csv", ".dat", ".npy", ".json", ".yaml", ".yml")
NUMBERS = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


@dataclass(frozen=True)
class PoseFormat:
    name: str
    count: int  # numbers per pose
    euler: tuple | None = None  # (scipy sequence, degrees)


@dataclass
class PoseRecord:
    number: int | None  # frame number from the file (column or name); None: by order
    matrix: np.ndarray  # 4x4 as written: translation in the file's unit
    where: str  # the file and line, for messages


def parse_format(fmt: str) -> PoseFormat:
    f = str(fmt).strip().lower()
    simple = {"matrix": 16, "xyz-quat-xyzw": 7, "xyz-quat-wxyz": 7, "xyz-rotvec": 6, "visp": 6}
    if f in simple:
        return PoseFormat(f, simple[f])
    m = re.fullmatch(r"xyz-euler:(fixed-)?([xyz]{3}):(deg|rad)", f)
    if not m:
        raise InputError("--pose-format", f"unknown pose format '{fmt}' (one of {FORMAT_HELP})")
    order = m.group(2)
    if order[0] == order[1] or order[1] == order[2]:
        raise InputError("--pose-format", f"'{order}' turns twice in a row about the same axis")
    # scipy: upper case turns about the moving axes (intrinsic), lower case about fixed ones
    seq = order if m.group(1) else order.upper()
    return PoseFormat(f, 6, (seq, m.group(3) == "deg"))


def to_matrix(values, fmt: PoseFormat, where: str) -> np.ndarray:
    """One pose's numbers -> 4x4 (translation in the file's unit)."""
    v = np.asarray(values, dtype=float).ravel()
    if v.size != fmt.count:
        raise InputError(where, f"expected {fmt.count} numbers for '{fmt.name}', got {v.size}")
    if not np.all(np.isfinite(v)):
        raise InputError(where, "NaN or Inf in the pose")
    M = np.eye(4)
    if fmt.name == "matrix":
        M = v.reshape(4, 4).copy()
        R = M[:3, :3]
        if not np.allclose(M[3], [0, 0, 0, 1], atol=1e-6):
            raise InputError(where, "the last row of a 4x4 pose must be 0 0 0 1, got "
                                    + " ".join(f"{x:g}" for x in M[3]))
        err = np.abs(R @ R.T - np.eye(3)).max()
        if err > 2e-3 or np.linalg.det(R) < 0:
            raise InputError(where, f"the 3x3 block is not a rotation (|R·Rᵀ - I| = {err:.2g}, "
                                    f"det {np.linalg.det(R):.3f})")
        return M
    M[:3, 3] = v[:3]
    if fmt.name.startswith("xyz-quat"):
        q = v[3:] if fmt.name == "xyz-quat-xyzw" else np.r_[v[4:], v[3]]
        norm = np.linalg.norm(q)
        if abs(norm - 1) > 1e-3:
            raise InputError(where, f"quaternion is not unit (norm {norm:.6g}); is the order "
                                    f"{'wxyz' if fmt.name.endswith('xyzw') else 'xyzw'}?")
        M[:3, :3] = Rotation.from_quat(q / norm).as_matrix()
    elif fmt.euler:
        M[:3, :3] = Rotation.from_euler(fmt.euler[0], v[3:], degrees=fmt.euler[1]).as_matrix()
    else:  # rotation vector (UR) or ViSP's theta-u: the same thing
        M[:3, :3] = Rotation.from_rotvec(v[3:]).as_matrix()
    return M


def frame_number(path) -> int | None:
    """The last number in a file name's stem (``im_07.png`` -> 7, ``pose_fPe_12.yaml`` -> 12)."""
    found = re.findall(r"\d+", Path(path).stem)
    return int(found[-1]) if found else None


def expand(spec: str, suffixes) -> list:
    """The files of a folder or a glob with one of ``suffixes``, sorted by name."""
    p = Path(spec)
    if p.is_dir():
        files = [f for f in p.iterdir() if f.is_file()]
    elif any(ch in spec for ch in "*?["):
        files = [Path(f) for f in glob.glob(spec) if Path(f).is_file()]
    else:
        raise InputError(spec, "no such folder, and not a glob")
    return sorted((f for f in files if f.suffix.lower() in suffixes), key=lambda f: f.name)


def _flatten_numbers(obj, where):
    if isinstance(obj, dict):
        if "data" in obj:  # ViSP / OpenCV matrices: rows, cols, data
            obj = obj["data"]
        else:
            lists = [v for v in obj.values() if isinstance(v, list)]
            if len(lists) != 1:
                raise InputError(where, "expected a list of numbers (or a mapping with one, e.g. 'data')")
            obj = lists[0]
    try:
        return np.asarray(obj, dtype=float).ravel()
    except (TypeError, ValueError):
        raise InputError(where, "expected numbers") from None


def _load_structured(path: Path):
    try:
        if path.suffix.lower() == ".npy":
            return np.load(path, allow_pickle=False)
        text = path.read_text(encoding="utf-8-sig")
        return json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (ValueError, yaml.YAMLError, UnicodeDecodeError, OSError) as e:
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise InputError(path, f"cannot be read ({first})") from None


def _text_rows(path: Path):
    """[(line number, [numbers])] of a text file: '#' comments and a leading header skipped."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (UnicodeDecodeError, OSError):
        raise InputError(path, "not a text file") from None
    rows = []
    for i, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        tokens = [t for t in re.split(r"[\s,;]+", line.strip("[]() ")) if t]
        try:
            rows.append((i, [float(t.strip("[]()")) for t in tokens]))
        except ValueError:
            if rows:
                raise InputError(path, f"not numbers: '{line[:60]}'", f"line {i}") from None
            continue  # a header
    return rows


def _records_from_text(path: Path, fmt: PoseFormat) -> list:
    rows = _text_rows(path)
    if not rows:
        raise InputError(path, "no poses in it")
    if len(rows) > 1 and all(len(r) < fmt.count and fmt.count % len(r) == 0 for _, r in rows):
        # poses over several lines: 4x4 blocks, column vectors
        starts, flat = [], []
        for i, r in rows:
            starts += [i] * len(r)
            flat += r
        if len(flat) % fmt.count:
            raise InputError(path, f"{len(flat)} numbers over lines shorter than a pose: not a whole number of "
                                   f"'{fmt.name}' poses ({fmt.count} numbers each)")
        return [PoseRecord(None, to_matrix(flat[k:k + fmt.count], fmt, f"{path}: line {starts[k]}"),
                           f"{path}: line {starts[k]}") for k in range(0, len(flat), fmt.count)]
    out = []
    for i, r in rows:
        where = f"{path}: line {i}"
        if len(r) == fmt.count + 1:
            if r[0] != int(r[0]) or r[0] < 0:
                raise InputError(path, f"the first of {len(r)} numbers is taken as the frame number, but it is "
                                       f"{r[0]:g}", f"line {i}")
            out.append(PoseRecord(int(r[0]), to_matrix(r[1:], fmt, where), where))
        elif len(r) == fmt.count:
            out.append(PoseRecord(None, to_matrix(r, fmt, where), where))
        else:
            raise InputError(path, f"expected {fmt.count} numbers for '{fmt.name}' (or {fmt.count + 1} with a "
                                   f"frame number first), got {len(r)}", f"line {i}")
    return out


def _records_from_structured(path: Path, fmt: PoseFormat) -> list:
    data = _load_structured(path)
    if isinstance(data, np.ndarray):
        one = data.ndim == 1 or (fmt.name == "matrix" and data.shape in ((4, 4), (3, 4)))
        arr = data.reshape(1, -1) if one else data.reshape(len(data), -1)
        if arr.shape[1] == 12 and fmt.name == "matrix":  # 3x4: the last row is implied
            arr = np.c_[arr, np.tile([0.0, 0, 0, 1], (len(arr), 1))]
        if arr.shape[1] != fmt.count:
            raise InputError(path, f"array of shape {data.shape}: expected (N, {fmt.count})"
                                   + (" or (N, 4, 4)" if fmt.name == "matrix" else ""))
        return [PoseRecord(None, to_matrix(a, fmt, f"{path}: pose {k}"), f"{path}: pose {k}")
                for k, a in enumerate(arr)]
    if isinstance(data, dict) and all(re.fullmatch(r"\D*\d+\D*", str(k)) for k in data) and "data" not in data:
        return [PoseRecord(frame_number(str(k)), to_matrix(_flatten_numbers(v, f"{path}: {k}"), fmt, f"{path}: {k}"),
                           f"{path}: {k}") for k, v in data.items()]
    if isinstance(data, list) and data and all(isinstance(x, (list, dict)) for x in data):
        flat = [_flatten_numbers(x, f"{path}: pose {k}") for k, x in enumerate(data)]
        if not (len(flat) in (3, 4) and all(f.size == 4 for f in flat)):  # not a single nested 4x4 / 3x4
            return [PoseRecord(None, to_matrix(f, fmt, f"{path}: pose {k}"), f"{path}: pose {k}")
                    for k, f in enumerate(flat)]
    return [PoseRecord(None, to_matrix(_flatten_numbers(data, str(path)), fmt, str(path)), str(path))]


def read_poses(spec: str, fmt: PoseFormat) -> list:
    """[PoseRecord] from ``--poses``: a file (several poses), or a folder or glob (one file each)."""
    p = Path(spec)
    if p.is_file():
        if p.suffix.lower() in (".npy", ".json", ".yaml", ".yml"):
            return _records_from_structured(p, fmt)
        return _records_from_text(p, fmt)
    files = expand(spec, PER_FRAME_SUFFIXES)
    if not files:
        raise InputError(spec, f"no pose files ({', '.join(PER_FRAME_SUFFIXES)}) in it")
    out = []
    for f in files:
        recs = _records_from_structured(f, fmt) if f.suffix.lower() in (".npy", ".json", ".yaml", ".yml") \
            else _records_from_text(f, fmt)
        if len(recs) != 1:
            raise InputError(f, f"one file per frame should hold one pose, this one holds {len(recs)}")
        out.append(PoseRecord(frame_number(f), recs[0].matrix, str(f)))
    return out
