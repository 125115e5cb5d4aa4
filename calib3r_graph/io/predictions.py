"""Reading and writing ``predictions/<name>/``: per-view canonical depth + confidence and
the co-visibility graph's pairwise matches (see docs/dataset-format.md)."""

import csv
import json
import logging
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib3r_graph.errors import InputError
from calib3r_graph.io.output import atomic_savez, atomic_write_json, staged_directory

log = logging.getLogger(__name__)


@dataclass
class ViewPrediction:
    depth: np.ndarray  # (h, w) float32, frontend units
    conf: np.ndarray  # (h, w) float32, >= 0
    K: np.ndarray  # (3, 3) intrinsics of the (h, w) grid


@dataclass
class PairMatches:
    view_a: str
    view_b: str
    uv_a: np.ndarray  # (n, 2)
    uv_b: np.ndarray  # (n, 2)
    conf: np.ndarray  # (n,)


@dataclass
class Predictions:
    name: str
    info: dict
    views: dict  # "camera/frame" -> ViewPrediction
    pairs: list  # [PairMatches]


def view_id(camera: str, frame: str) -> str:
    return f"{camera}/{frame}"


def split_view_id(vid: str) -> tuple[str, str]:
    camera, frame = vid.split("/", 1)
    return camera, frame


def _load_npz(path: Path, required: dict) -> dict:
    """Load an npz and check each required key's dtype kind and number of dimensions."""
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, zlib.error, EOFError, KeyError) as e:
        raise InputError(path, f"unreadable npz ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None
    for key, (kinds, ndim) in required.items():
        if key not in data:
            raise InputError(path, f"missing array '{key}'", key)
        a = data[key]
        if a.dtype.kind not in kinds or a.ndim != ndim:
            raise InputError(path, f"'{key}' must be a {ndim}-d array of kind {kinds}, got {a.dtype} {a.shape}", key)
    return data


def load_view(path: Path) -> ViewPrediction:
    d = _load_npz(path, {"depth": ("f", 2), "conf": ("f", 2), "K": ("f", 2)})
    depth, conf, K = d["depth"].astype(np.float32), d["conf"].astype(np.float32), d["K"].astype(np.float64)
    if conf.shape != depth.shape:
        raise InputError(path, f"conf shape {conf.shape} differs from depth shape {depth.shape}", "conf")
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, "K must be a finite 3x3 matrix with positive focal lengths", "K")
    if depth.size == 0:
        raise InputError(path, "empty depth map", "depth")
    if np.any(conf < 0) or np.any(np.isnan(conf)):
        raise InputError(path, "conf must be >= 0 and not NaN", "conf")
    # Non-finite or non-positive depth is "no depth here": confidence zero, never used.
    bad = ~np.isfinite(depth) | (depth <= 0)
    if bad.all():
        raise InputError(path, "no valid (finite, positive) depth", "depth")
    depth = np.where(bad, 0.0, depth).astype(np.float32)
    conf = np.where(bad, 0.0, conf).astype(np.float32)
    return ViewPrediction(depth, conf, K)


def load_predictions(root, name: str, cameras=None, frames=None, skip_missing: bool = False) -> Predictions:
    """Load ``root/predictions/<name>`` and validate it against the dataset's cameras and frames.

    With ``skip_missing``, views of frames without a robot pose are dropped with a warning
    (and so are the pairs that reference them) instead of being an error.
    """
    pdir = Path(root) / "predictions" / name
    if not pdir.is_dir():
        raise InputError(pdir, "no such predictions directory")
    info_path = pdir / "info.json"
    info = {}
    if info_path.is_file():
        try:
            info = json.loads(info_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise InputError(info_path, f"not valid JSON ({e})") from None
        if not isinstance(info, dict):
            raise InputError(info_path, "must be a JSON object")
    views, skipped = {}, set()
    vdir = pdir / "views"
    if vdir.is_dir():
        for cam_dir in sorted(p for p in vdir.iterdir() if p.is_dir()):
            for f in sorted(cam_dir.glob("*.npz")):
                if cameras is not None and cam_dir.name not in cameras:
                    raise InputError(f, f"unknown camera '{cam_dir.name}' (not in dataset.yaml)")
                if frames is not None and f.stem not in frames:
                    if skip_missing:
                        log.warning("%s: frame %s has no robot pose; skipped", f, f.stem)
                        skipped.add(view_id(cam_dir.name, f.stem))
                        continue
                    raise InputError(f, f"frame {f.stem} has no row in robot_poses.csv "
                                        "(use --skip-missing to drop such frames)")
                views[view_id(cam_dir.name, f.stem)] = load_view(f)
    if not views:
        raise InputError(vdir, "no view predictions (views/<camera>/<frame>.npz)")
    pairs = load_pairs(pdir / "pairs.npz", views, skipped)
    return Predictions(name, info, views, pairs)


def load_pairs(path: Path, views: dict, skipped=frozenset()) -> list:
    if not path.is_file():
        raise InputError(path, "missing (the co-visibility graph's matches)")
    d = _load_npz(path, {"view_a": ("US", 1), "view_b": ("US", 1), "offsets": ("iu", 1),
                         "uv_a": ("f", 2), "uv_b": ("f", 2), "conf": ("f", 1)})
    va, vb, off = d["view_a"], d["view_b"], d["offsets"].astype(np.int64)
    uv_a, uv_b, conf = d["uv_a"], d["uv_b"], d["conf"]
    n_edges, n_matches = len(va), len(uv_a)
    if len(vb) != n_edges or len(off) != n_edges + 1:
        raise InputError(path, f"view_a ({len(va)}), view_b ({len(vb)}) and offsets ({len(off)}) must have E, E, E+1 rows")
    if uv_a.shape != (n_matches, 2) or uv_b.shape != (n_matches, 2) or conf.shape != (n_matches,):
        raise InputError(path, f"uv_a {uv_a.shape}, uv_b {uv_b.shape}, conf {conf.shape} must be (P,2), (P,2), (P,)")
    if n_edges and (off[0] != 0 or off[-1] != n_matches or np.any(np.diff(off) < 0)):
        raise InputError(path, "offsets must start at 0, never decrease and end at the number of matches", "offsets")
    if not (np.all(np.isfinite(uv_a)) and np.all(np.isfinite(uv_b)) and np.all(np.isfinite(conf))):
        raise InputError(path, "non-finite match coordinates or confidences")
    pairs = []
    for e in range(n_edges):
        a, b = str(va[e]), str(vb[e])
        if a in skipped or b in skipped:
            continue
        for v in (a, b):
            if v not in views:
                raise InputError(path, f"edge {e} references unknown view '{v}'", "view_a/view_b")
        if a == b:
            raise InputError(path, f"edge {e} pairs view '{a}' with itself")
        s = slice(off[e], off[e + 1])
        if off[e + 1] == off[e]:
            continue  # an edge without matches carries no information
        pairs.append(PairMatches(a, b, uv_a[s].astype(np.float64), uv_b[s].astype(np.float64), conf[s].astype(np.float64)))
    if not pairs:
        raise InputError(path, "no matches in any pair")
    return pairs


def save_predictions(root, name: str, views: dict, pairs: list, info: dict):
    """Write ``root/predictions/<name>/`` atomically (a failed write leaves any old cache intact)."""
    with staged_directory(Path(root) / "predictions" / name) as stage:
        for vid, v in views.items():
            cam, frame = split_view_id(vid)
            atomic_savez(stage / "views" / cam / f"{frame}.npz", depth=v.depth.astype(np.float32),
                         conf=v.conf.astype(np.float32), K=np.asarray(v.K, np.float64))
        sizes = [len(p.uv_a) for p in pairs]
        atomic_savez(stage / "pairs.npz",
                     view_a=np.array([p.view_a for p in pairs]), view_b=np.array([p.view_b for p in pairs]),
                     offsets=np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
                     uv_a=np.concatenate([p.uv_a for p in pairs]).astype(np.float32),
                     uv_b=np.concatenate([p.uv_b for p in pairs]).astype(np.float32),
                     conf=np.concatenate([p.conf for p in pairs]).astype(np.float32))
        atomic_write_json(stage / "info.json", info)


def subset_predictions(preds: Predictions, frames) -> Predictions:
    """The predictions restricted to the views of the given frames, and the pairs among them."""
    frames = set(frames)
    views = {v: p for v, p in preds.views.items() if split_view_id(v)[1] in frames}
    pairs = [p for p in preds.pairs if p.view_a in views and p.view_b in views]
    return Predictions(preds.name, preds.info, views, pairs)


def read_poses_csv(path: Path) -> dict:
    """A frontend's visual poses, ``predictions/<name>/poses.csv`` -> {view: world_T_cam 4x4
    (frontend units)}. Written by the colmap frontend."""
    if not path.is_file():
        raise InputError(path, "missing: --init colmap needs predictions made by the colmap frontend")
    out = {}
    i = 1
    try:
        rows = list(csv.reader(path.read_text().splitlines()))
        for i, row in enumerate(rows[1:], start=2):
            T = np.eye(4)
            T[:3] = np.array([float(x) for x in row[1:13]]).reshape(3, 4)
            out[row[0]] = T
    except (ValueError, IndexError) as e:
        raise InputError(path, f"row {i}: not a pose ({e})") from None
    return out


def available_predictions(root) -> list:
    pdir = Path(root) / "predictions"
    return sorted(p.name for p in pdir.iterdir() if p.is_dir() and not p.name.startswith(".")) if pdir.is_dir() else []


def choose_predictions(ds, name: str | None) -> str:
    """The predictions to solve from: the one named, else the only one (or 'sim' among several)."""
    from calib3r_graph.errors import SolveError

    have = available_predictions(ds.root)
    if name is not None:
        if name not in have:
            raise InputError(Path(ds.root) / "predictions" / name,
                             f"no such predictions (available: {', '.join(have) or 'none'})")
        return name
    if not have:
        raise SolveError(f"{ds.root}: no predictions/ to solve from; make some with "
                         "'calib3r-graph predict DATASET --frontend rgbd|pairwise|colmap'")
    if len(have) == 1:
        return have[0]
    for preferred in ("sim", "rgbd", "pairwise", "colmap"):
        if preferred in have:
            return preferred
    raise SolveError(f"{ds.root}: several predictions ({', '.join(have)}); choose one with --predictions")
