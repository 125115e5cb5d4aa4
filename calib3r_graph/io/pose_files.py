"""Robot pose files: the formats controllers and tools write, read into 4x4 matrices.

Formats (``--pose-format``), translation first, in the file's unit:

* ``matrix``: a 4x4 matrix (16 numbers, row- or column-major as they show; or four lines of four);
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
  number in its name, or, where the names do not tell the frames apart (every file ``data.json``),
  in the nearest parent folder's name that does (``pose_07/data.json`` -> 7); a folder without
  such files is searched one level down (per-frame folders).

In a JSON or YAML mapping (Franka's per-frame ``data.json``) the pose is the entry named by
``--pose-key`` (dots for nested keys: ``robot.O_T_EE``), else the only entry holding a pose's
count of numbers, else a known key (``O_T_EE``, libfranka's flange pose). A 4x4 given as 16
numbers is read row-major or column-major (libfranka documents O_T_EE as column-major), as its
numbers show: a homogeneous matrix's last row 0 0 0 1 sits at indices 12-15 row-major, at 3, 7,
11, 15 column-major; all poses of an import must agree.

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
KNOWN_POSE_KEYS = ("O_T_EE",)  # libfranka / franky: the flange in the robot's base frame
LAST_ROW = {"row-major": [12, 13, 14, 15], "column-major": [3, 7, 11, 15]}  # where 0 0 0 1 sits


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
    key: str | None = None  # the mapping entry the pose was read from, and why (``how``)
    how: str = ""
    layouts: frozenset = frozenset()  # a 16-number matrix: the layouts its numbers allow


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


def matrix_layouts(values) -> frozenset:
    """The layouts ('row-major', 'column-major') under which 16 numbers are a homogeneous 4x4."""
    v = np.asarray(values, dtype=float).ravel()
    return frozenset(k for k, idx in LAST_ROW.items() if np.allclose(v[idx], [0, 0, 0, 1], atol=1e-6))


def to_matrix(values, fmt: PoseFormat, where: str, layout: str = "row-major") -> np.ndarray:
    """One pose's numbers -> 4x4 (translation in the file's unit); a matrix in ``layout``."""
    v = np.asarray(values, dtype=float).ravel()
    if v.size != fmt.count:
        raise InputError(where, f"expected {fmt.count} numbers for '{fmt.name}', got {v.size}")
    if not np.all(np.isfinite(v)):
        raise InputError(where, "NaN or Inf in the pose")
    M = np.eye(4)
    if fmt.name == "matrix":
        M = v.reshape(4, 4).copy() if layout == "row-major" else v.reshape(4, 4).T.copy()
        R = M[:3, :3]
        if not np.allclose(M[3], [0, 0, 0, 1], atol=1e-6):
            raise InputError(where, "the last row of a 4x4 pose must be 0 0 0 1 (numbers 13-16 row-major, 4, 8, 12, "
                                    "16 column-major), got " + " ".join(f"{x:g}" for x in M[3]))
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


def to_numbers(M, fmt: PoseFormat, layout: str = "row-major") -> np.ndarray:
    """:func:`to_matrix`'s inverse: a 4x4 (translation in the file's unit) as the format's numbers, so
    that a pose the tool proposes can be given to the robot as its own file writes poses. A
    quaternion has w >= 0; Euler angles are scipy's (the middle angle in [-90, 90] deg for an order
    of three different axes, in [0, 180] for one that repeats the first; at that angle's limit, where
    the first and third turn about one axis, the third is 0)."""
    import warnings

    M = np.asarray(M, dtype=float)
    if fmt.name == "matrix":
        return (M if layout == "row-major" else M.T).ravel().copy()
    R = Rotation.from_matrix(M[:3, :3])
    if fmt.name.startswith("xyz-quat"):
        q = R.as_quat(canonical=True)  # x y z w
        rot = q if fmt.name == "xyz-quat-xyzw" else np.r_[q[3], q[:3]]
    elif fmt.euler:
        with warnings.catch_warnings():  # gimbal lock: one of many decompositions, the same matrix
            warnings.simplefilter("ignore", UserWarning)
            rot = R.as_euler(fmt.euler[0], degrees=fmt.euler[1])
    else:
        rot = R.as_rotvec()
    return np.r_[M[:3, 3], rot]


def column_names(fmt: PoseFormat, layout: str = "row-major") -> list:
    """Names for :func:`to_numbers`' columns (a CSV header): ``x y z`` first, then the rotation's."""
    if fmt.name == "matrix":
        idx = [(i, j) for i in range(4) for j in range(4)]
        return [f"m{i}{j}" for i, j in (idx if layout == "row-major" else [(j, i) for i, j in idx])]
    rot = {"xyz-quat-xyzw": ["qx", "qy", "qz", "qw"], "xyz-quat-wxyz": ["qw", "qx", "qy", "qz"],
           "xyz-rotvec": ["rx", "ry", "rz"], "visp": ["tux", "tuy", "tuz"]}.get(fmt.name, ["a", "b", "c"])
    return ["x", "y", "z", *rot]


def _last_number(name: str) -> int | None:
    found = re.findall(r"\d+", name)
    return int(found[-1]) if found else None


def frame_number(path) -> int | None:
    """The last number in a file name's stem (``im_07.png`` -> 7, ``pose_fPe_12.yaml`` -> 12)."""
    return _last_number(Path(path).stem)


def frame_numbers(paths) -> list | None:
    """The files' frame numbers: the last number in each name's stem where those tell the files
    apart, else in the nearest parent folder's name that does (``pose_07/image.png`` -> 7);
    None when no level numbers every file once."""
    paths = [Path(p) for p in paths]
    for level in range(max((len(p.parents) for p in paths), default=0)):
        names = [p.stem if level == 0 else p.parents[level - 1].name if level <= len(p.parents) else "" for p in paths]
        nums = [_last_number(n) for n in names]
        if None not in nums and len(set(nums)) == len(nums):
            return nums
    return None


def _natural(path: Path):
    """Sort key: numbers by value (pose_2 before pose_10), the rest as text."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(path))]


def expand(spec: str, suffixes) -> list:
    """The files of a folder (or of its subfolders, one per frame, when it holds none itself) or of a
    glob with one of ``suffixes``, in natural order of their paths."""
    p = Path(spec)

    def keep(files):
        return [f for f in files if f.is_file() and f.suffix.lower() in suffixes]

    if p.is_dir():
        files = keep(p.iterdir()) or keep(f for d in p.iterdir() if d.is_dir() for f in d.iterdir())
    elif any(ch in spec for ch in "*?["):
        files = keep(Path(f) for f in glob.glob(spec))
    else:
        raise InputError(spec, "no such folder, and not a glob")
    return sorted(files, key=_natural)


def _numbers(obj):
    """The numbers of a list (nested: a 4x4) or of an OpenCV/ViSP matrix node ({rows, cols, data}); None if not."""
    if isinstance(obj, dict):
        obj = obj.get("data") if "data" in obj else None
    if obj is None or isinstance(obj, (str, bool)):
        return None
    try:
        return np.asarray(obj, dtype=float).ravel()
    except (TypeError, ValueError):
        return None


def _entries(obj, prefix=""):
    """{dotted key: numbers or None} of a mapping's leaves (nested mappings walked)."""
    out = {}
    for k, v in obj.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict) and "data" not in v:
            out.update(_entries(v, name + "."))
        else:
            out[name] = _numbers(v)
    return out


def _listing(entries) -> str:
    shown = [f"{k} ({'not numbers' if n is None else f'{n.size} numbers'})" for k, n in list(entries.items())[:12]]
    return ", ".join(shown) + (f" and {len(entries) - 12} more" if len(entries) > 12 else "")


def _pose_numbers(obj, fmt: PoseFormat, where, key=None) -> tuple:
    """(numbers, key, how) of one pose: a list, or a mapping's entry (``key``: dotted, as given)."""
    if not isinstance(obj, dict) or "data" in obj:  # a list, or ViSP's / OpenCV's {rows, cols, data}
        if key and isinstance(obj, dict):
            raise InputError(where, f"no key '{key}' (--pose-key): it holds {_listing(_entries(obj))}")
        v = _numbers(obj)
        if v is None:
            raise InputError(where, "expected numbers")
        return v, None, ""
    entries = _entries(obj)
    if key:
        if key not in entries:
            raise InputError(where, f"no key '{key}' (--pose-key); keys found: {_listing(entries)}")
        if entries[key] is None:
            raise InputError(where, f"'{key}' does not hold numbers")
        return entries[key], key, "named by --pose-key"
    fits = [k for k, v in entries.items() if v is not None and v.size == fmt.count]
    if len(fits) == 1:
        return entries[fits[0]], fits[0], f"the only entry of {fmt.count} numbers"
    known = [k for k in entries if k.split(".")[-1] in KNOWN_POSE_KEYS and entries[k] is not None]
    if len(known) == 1:
        return entries[known[0]], known[0], "a known pose key"
    raise InputError(where, f"{len(fits) or 'no'} entries of {fmt.count} numbers ('{fmt.name}'): name the pose's entry "
                            f"with --pose-key (dots for nested keys); keys found: {_listing(entries)}")


def _record(number, values, fmt: PoseFormat, where: str, key=None, how="") -> PoseRecord:
    """A pose record; a 16-number matrix read in the one layout its numbers allow (row-major if both)."""
    v = np.asarray(values, dtype=float).ravel()
    layouts = matrix_layouts(v) if fmt.name == "matrix" and v.size == 16 else frozenset()
    layout = "column-major" if layouts == {"column-major"} else "row-major"
    return PoseRecord(number, to_matrix(v, fmt, where, layout), where, key, how, layouts)


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
        return [_record(None, flat[k:k + fmt.count], fmt, f"{path}: line {starts[k]}")
                for k in range(0, len(flat), fmt.count)]
    out = []
    for i, r in rows:
        where = f"{path}: line {i}"
        if len(r) == fmt.count + 1:
            if r[0] != int(r[0]) or r[0] < 0:
                raise InputError(path, f"the first of {len(r)} numbers is taken as the frame number, but it is "
                                       f"{r[0]:g}", f"line {i}")
            out.append(_record(int(r[0]), r[1:], fmt, where))
        elif len(r) == fmt.count:
            out.append(_record(None, r, fmt, where))
        else:
            raise InputError(path, f"expected {fmt.count} numbers for '{fmt.name}' (or {fmt.count + 1} with a "
                                   f"frame number first), got {len(r)}", f"line {i}")
    return out


def _records_from_structured(path: Path, fmt: PoseFormat, key=None) -> list:
    data = _load_structured(path)
    if isinstance(data, np.ndarray):
        one = data.ndim == 1 or (fmt.name == "matrix" and data.shape in ((4, 4), (3, 4)))
        arr = data.reshape(1, -1) if one else data.reshape(len(data), -1)
        if arr.shape[1] == 12 and fmt.name == "matrix":  # 3x4: the last row is implied
            arr = np.c_[arr, np.tile([0.0, 0, 0, 1], (len(arr), 1))]
        if arr.shape[1] != fmt.count:
            raise InputError(path, f"array of shape {data.shape}: expected (N, {fmt.count})"
                                   + (" or (N, 4, 4)" if fmt.name == "matrix" else ""))
        return [_record(None, a, fmt, f"{path}: pose {k}") for k, a in enumerate(arr)]

    def one(number, obj, where):
        values, used, how = _pose_numbers(obj, fmt, where, key)
        return _record(number, values, fmt, where, used, how)

    if isinstance(data, dict) and all(re.fullmatch(r"\D*\d+\D*", str(k)) for k in data) and "data" not in data:
        return [one(frame_number(str(k)), v, f"{path}: {k}") for k, v in data.items()]
    if isinstance(data, list) and data and all(isinstance(x, (list, dict)) for x in data):
        if not (len(data) in (3, 4) and all(isinstance(x, list) and len(x) == 4 for x in data)):  # not one 4x4 / 3x4
            return [one(None, x, f"{path}: pose {k}") for k, x in enumerate(data)]
    return [one(None, data, str(path))]


def _check_layouts(records: list) -> list:
    """One layout for every 16-number matrix: an error when the files mix them or a pose fits neither."""
    mats = [r for r in records if r.layouts]
    found = {k: next((r for r in mats if r.layouts == {k}), None) for k in LAST_ROW}
    if all(found.values()):
        raise InputError(found["column-major"].where, "this 4x4 is column-major (0 0 0 1 at numbers 4, 8, 12, 16) but "
                                                      f"{found['row-major'].where} is row-major: one layout for all")
    if found["column-major"]:  # the poses that fit both (no translation) are read column-major too
        for r in mats:
            if len(r.layouts) == 2:
                r.matrix, r.layouts = r.matrix.T.copy(), frozenset({"column-major"})
    return records


def layout_of(records: list) -> str | None:
    """'row-major' or 'column-major' for 16-number matrices, else None."""
    return next((("column-major" if r.layouts == {"column-major"} else "row-major") for r in records if r.layouts),
                None)


def describe(records: list) -> str:
    """How the poses were read: the key (and why) and the matrices' layout, for the import report."""
    parts = []
    keyed = [r for r in records if r.key]
    if keyed:
        keys = sorted({r.key for r in keyed})
        parts.append(f"pose under '{', '.join(keys)}' ({keyed[0].how})")
    layout = layout_of(records)
    if layout:
        parts.append(f"4x4 read {layout} (0 0 0 1 at numbers "
                     f"{', '.join(str(i + 1) for i in LAST_ROW[layout])})")
    return "; ".join(parts)


def read_poses(spec: str, fmt: PoseFormat, key: str | None = None) -> list:
    """[PoseRecord] from ``--poses``: a file (several poses), or a folder or glob (one file each).
    ``key``: the entry of a JSON/YAML mapping that holds the pose (dotted for nested keys)."""
    p = Path(spec)
    files = [p] if p.is_file() else expand(spec, PER_FRAME_SUFFIXES)
    text = next((f for f in files if f.suffix.lower() not in (".json", ".yaml", ".yml")), None)
    if key and text is not None:
        raise InputError(text, f"--pose-key '{key}' names an entry of a JSON or YAML file, and this is not one")
    if p.is_file():
        if p.suffix.lower() in (".npy", ".json", ".yaml", ".yml"):
            return _check_layouts(_records_from_structured(p, fmt, key))
        return _check_layouts(_records_from_text(p, fmt))
    if not files:
        raise InputError(spec, f"no pose files ({', '.join(PER_FRAME_SUFFIXES)}) in it")
    out = []
    for f, n in zip(files, frame_numbers(files) or [None] * len(files)):
        recs = _records_from_structured(f, fmt, key) if f.suffix.lower() in (".npy", ".json", ".yaml", ".yml") \
            else _records_from_text(f, fmt)
        if len(recs) != 1:
            raise InputError(f, f"one file per frame should hold one pose, this one holds {len(recs)}")
        recs[0].number, recs[0].where = n, str(f)
        out.append(recs[0])
    return _check_layouts(out)
