"""Converters from foundation-model outputs saved where the models run (a GPU machine) into
``predictions/<name>/``. No model runs here and no weights are downloaded.

Supported files (see docs/frontends.md for the export snippets):

* **VGGT** ``predictions.npz`` as its demo saves it: ``depth`` (S, H, W, 1),
  ``depth_conf`` (S, H, W), ``extrinsic`` (S, 3, 4) camera-from-world, ``intrinsic``
  (S, 3, 3), optionally ``image_names`` (S,) — else give ``--order``.
* **DUSt3R** global alignment / **MASt3R** sparse GA, exported to an npz with
  ``image_names`` (N,), ``depthmaps`` (N, H, W) — or (N, P, H, W) with P pairwise
  predictions per view, aggregated by confidence (eq. 1) — ``conf`` (same shape), ``cam2w`` (N, 4, 4),
  ``focals`` (N,) and ``pp`` (N, 2); MASt3R's own correspondences may be added in the
  pairs.npz layout (``view_a``, ``view_b``, ``offsets``, ``uv_a``, ``uv_b``, ``match_conf``).

The networks see resized/cropped images; the converter maps the dataset's calibrated
intrinsics through the same resize and crop onto the network grid (the networks' own
focal estimates are only used to build matches). Without stored correspondences,
matches are derived from the model's own geometry: each view's confident pixels are
lifted with its depth and pose, projected into the other view, and kept where they
agree with that view's depth (3 %), on a top-k co-visibility graph.
"""

import logging
from pathlib import Path

import numpy as np

from calib3r_graph.errors import InputError
from calib3r_graph.frontends.common import aggregate_pointmaps, covisibility_edges
from calib3r_graph.io.predictions import PairMatches, ViewPrediction, save_predictions, view_id

log = logging.getLogger(__name__)


def vggt_grid(width, height, mode="crop", target=518):
    """(sx, sy, off_x, off_y, w, h): grid u = (u_img + 0.5) * sx - 0.5 - off_x (VGGT load_and_preprocess_images)."""
    if mode == "pad" and height > width:
        new_h, new_w = target, round(width * (target / height) / 14) * 14
    else:
        new_w, new_h = target, round(height * (target / width) / 14) * 14
    sx, sy = new_w / width, new_h / height
    if mode == "crop":
        off_y = (new_h - target) // 2 if new_h > target else 0
        return sx, sy, 0.0, float(off_y), new_w, min(new_h, target)
    pad_x, pad_y = (target - new_w) // 2, (target - new_h) // 2  # negative offsets: padding
    return sx, sy, -float(pad_x), -float(pad_y), target, target


def dust3r_grid(width, height, size=512, square_ok=False):
    """Same for DUSt3R / MASt3R load_images(size=512): long side to 512, centre crop to multiples of 16."""
    S = max(width, height)
    W, H = round(width * size / S), round(height * size / S)
    cx, cy = W // 2, H // 2
    halfw, halfh = ((2 * cx) // 16) * 8, ((2 * cy) // 16) * 8
    if not square_ok and W == H:
        halfh = 3 * halfw / 4
    return W / width, H / height, float(cx - halfw), float(cy - halfh), int(2 * halfw), int(2 * halfh)


def grid_intrinsics(K, grid):
    sx, sy, ox, oy, _, _ = grid
    Kg = np.array(K, dtype=np.float64).copy()
    Kg[0, 0], Kg[1, 1] = K[0, 0] * sx, K[1, 1] * sy
    Kg[0, 2] = (K[0, 2] + 0.5) * sx - 0.5 - ox
    Kg[1, 2] = (K[1, 2] + 0.5) * sy - 0.5 - oy
    return Kg


def _view_of(name: str, ds) -> str:
    """'.../images/cam0/0007.png' -> 'cam0/0007' (camera = parent folder, frame = stem)."""
    p = Path(str(name))
    cam, frame = p.parent.name, p.stem
    if cam not in ds.cameras and len(ds.cameras) == 1:
        cam = next(iter(ds.cameras))
    if cam not in ds.cameras or frame not in ds.base_T_ee:
        raise InputError(name, f"cannot map image '{name}' to a camera/frame of the dataset "
                               f"(expected .../<camera>/<frame>.<ext>)")
    return view_id(cam, frame)


def geometric_matches(depth, conf, K_model, cam2w, a, b, stride=4, max_matches=3000, rng=None):
    """Matches a -> b implied by the model's own depth and poses, mutually consistent in depth."""
    rng = rng or np.random.default_rng(0)
    h, w = depth[a].shape
    v, u = np.mgrid[0:h:stride, 0:w:stride]
    u, v = u.ravel().astype(np.float64), v.ravel().astype(np.float64)
    d = depth[a][v.astype(int), u.astype(int)]
    c = conf[a][v.astype(int), u.astype(int)]
    ok = (d > 0) & (c >= np.median(conf[a][conf[a] > 0]))
    u, v, d, c = u[ok], v[ok], d[ok], c[ok]
    P = np.c_[u, v, np.ones(len(u))] @ np.linalg.inv(K_model[a]).T * d[:, None]
    b_T_a = np.linalg.inv(cam2w[b]) @ cam2w[a]
    Q = P @ b_T_a[:3, :3].T + b_T_a[:3, 3]
    z = Q[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv_b = (Q @ K_model[b].T)[:, :2] / z[:, None]
    inside = (z > 0) & (uv_b[:, 0] >= 0) & (uv_b[:, 0] <= w - 1) & (uv_b[:, 1] >= 0) & (uv_b[:, 1] <= h - 1)
    ib = np.round(uv_b[inside]).astype(int)
    agree = np.zeros(len(u), bool)
    agree[inside] = np.abs(depth[b][ib[:, 1], ib[:, 0]] - z[inside]) < 0.03 * z[inside]
    idx = np.flatnonzero(agree)
    if len(idx) > max_matches:
        idx = rng.choice(idx, max_matches, replace=False)
    cb = conf[b][np.round(uv_b[idx, 1]).astype(int), np.round(uv_b[idx, 0]).astype(int)]
    return np.c_[u[idx], v[idx]], uv_b[idx], np.sqrt(c[idx] * cb)


def _normalise_conf(conf):
    """Confidences >= 0 with median 1 (DUSt3R-family confidences start at 1 and grow)."""
    conf = np.maximum(np.nan_to_num(conf, nan=0.0), 0)
    med = np.median(conf[conf > 0]) if np.any(conf > 0) else 1.0
    return (conf / med).astype(np.float32)


def convert(kind: str, path, ds, name=None, order=None, vggt_mode="crop", neighbours=5, max_matches=3000) -> str:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    try:
        z = dict(np.load(path, allow_pickle=False))
    except Exception as e:  # noqa: BLE001 - any unreadable file is an input error
        raise InputError(path, f"unreadable npz ({type(e).__name__})") from None
    names = list(z["image_names"]) if "image_names" in z else None
    if order is not None:
        names = [l.strip() for l in Path(order).read_text().splitlines() if l.strip()]
    if names is None:
        raise InputError(path, "no 'image_names' array: pass --order FILE listing the images in model order")
    if kind == "vggt":
        for k in ("depth", "depth_conf", "extrinsic", "intrinsic"):
            if k not in z:
                raise InputError(path, f"missing array '{k}' (expected VGGT predictions.npz)", k)
        depth = z["depth"][..., 0] if z["depth"].ndim == 4 else z["depth"]
        conf = z["depth_conf"]
        cam2w = np.array([np.linalg.inv(np.vstack([e, [0, 0, 0, 1]])) for e in z["extrinsic"]])
        K_model = z["intrinsic"].astype(np.float64)
        grid_of = lambda cam: vggt_grid(cam.width, cam.height, vggt_mode)
    elif kind in ("dust3r", "mast3r"):
        for k in ("depthmaps", "conf", "cam2w", "focals", "pp"):
            if k not in z:
                raise InputError(path, f"missing array '{k}' (see the {kind} export snippet in docs/frontends.md)", k)
        depth, conf, cam2w = z["depthmaps"], z["conf"], z["cam2w"].astype(np.float64)
        if depth.ndim == 4:  # (N, P, H, W): P pairwise predictions per view -> canonical (eq. 1)
            agg = [aggregate_pointmaps(d, c) for d, c in zip(depth, conf)]
            depth, conf = np.stack([a[0] for a in agg]), np.stack([a[1] for a in agg])
        f, pp = np.ravel(z["focals"]).astype(np.float64), z["pp"].astype(np.float64)
        K_model = np.array([[[fi, 0, p[0]], [0, fi, p[1]], [0, 0, 1]] for fi, p in zip(f, pp)])
        grid_of = lambda cam: dust3r_grid(cam.width, cam.height)
    else:
        raise InputError(kind, "unknown model (vggt, dust3r or mast3r)")
    n = len(depth)
    if not (len(names) == n == len(conf) == len(cam2w) == len(K_model)) or depth.shape != conf.shape:
        raise InputError(path, f"inconsistent sizes: {len(names)} names, depth {depth.shape}, conf {conf.shape}, "
                               f"poses {len(cam2w)}, intrinsics {len(K_model)}")
    vids = [_view_of(nm, ds) for nm in names]
    views = {}
    for i, vid in enumerate(vids):
        cam = ds.cameras[vid.split("/")[0]]
        grid = grid_of(cam)
        if depth[i].shape != (grid[5], grid[4]):
            raise InputError(path, f"{names[i]}: depth is {depth[i].shape[1]}x{depth[i].shape[0]} but "
                                   f"{kind} preprocessing of a {cam.width}x{cam.height} image gives "
                                   f"{grid[4]}x{grid[5]} (wrong --vggt-mode or camera size?)")
        views[vid] = ViewPrediction(depth[i].astype(np.float32), _normalise_conf(conf[i]), grid_intrinsics(cam.K, grid))
    if "view_a" in z and "uv_a" in z:
        off = z["offsets"]
        pairs = [PairMatches(str(z["view_a"][e]), str(z["view_b"][e]), z["uv_a"][off[e]:off[e + 1]].astype(float),
                             z["uv_b"][off[e]:off[e + 1]].astype(float),
                             z["match_conf"][off[e]:off[e + 1]].astype(float)) for e in range(len(off) - 1)]
    else:
        rng = np.random.default_rng(0)
        cand = {}
        for i in range(n):
            for j in range(i + 1, n):
                m = geometric_matches(depth, conf, K_model, cam2w, i, j, max_matches=max_matches, rng=rng)
                if len(m[0]) >= 30:
                    cand[(vids[i], vids[j])] = m
        edges = covisibility_edges({e: len(m[0]) for e, m in cand.items()}, sorted(vids), neighbours)
        pairs = [PairMatches(a, b, *cand[(a, b)]) if (a, b) in cand else
                 PairMatches(b, a, *cand[(b, a)]) for a, b in edges]
    if not pairs:
        raise InputError(path, "no two views overlap according to the model's geometry")
    name = name or kind
    save_predictions(ds.root, name, views, pairs, {"source": f"{kind} export {path.name} (calib3r-graph convert)",
                                                   "metric_depth": False, "match_noise_px": 1.0,
                                                   "network_grid": [int(x) for x in grid_of(next(iter(ds.cameras.values())))[4:]]})
    log.info("%s: %d views, %d pairs", kind, len(views), len(pairs))
    return name
