"""The cross-view surface disagreement: a check of the hand-eye that needs no board.

Each view's depth map is placed in the base frame by the robot's chain ``base_T_ee · ee_T_cam`` (not by
the solve's own view pose). With the right ee_T_cam (and a good robot) the views' surfaces coincide;
with a wrong one each view's surface moves by ``R_ee δt`` and ``z δθ`` in its own direction and the
surfaces double. For every neighbour pair (a, b), a's points are projected into b; where b has depth
there, the distance of a's point to b's local surface plane (b's normal) is one sample. The report is
the median and 90th percentile over all samples, in mm.
"""

import numpy as np

# A sample whose depth differs from b's by more than this share of the depth is an occlusion or a
# different surface, not a disagreement: 5 % is 25 mm at 0.5 m, five times the largest hand-eye error
# the check is meant to see (5 mm, 0.5 deg = 4.4 mm at 0.5 m).
OCCLUSION_REL = 0.05
SAMPLE_STRIDE = 3  # every 3rd pixel in each direction of a: neighbouring pixels' samples are correlated


def camera_points(depth: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """(h, w, 3) points in the camera frame (NaN where no depth)."""
    return rays * depth[..., None]


def normals(points: np.ndarray) -> np.ndarray:
    """(h, w, 3) unit normals of a camera-frame point grid (central differences; NaN at edges/holes),
    facing the camera."""
    n = np.full(points.shape, np.nan)
    dx = points[1:-1, 2:] - points[1:-1, :-2]
    dy = points[2:, 1:-1] - points[:-2, 1:-1]
    c = np.cross(dx, dy)
    with np.errstate(invalid="ignore", divide="ignore"):
        c /= np.linalg.norm(c, axis=-1, keepdims=True)
        c *= -np.sign(np.sum(c * points[1:-1, 1:-1], -1, keepdims=True))
    n[1:-1, 1:-1] = c
    return n


def disagreement(depths: dict, rays: dict, views: dict, neighbours: dict, poses: dict | None = None,
                 per_pair: bool = False) -> dict:
    """Median and p90 (mm) of the cross-view surface distance, with ``poses`` {view: 4x4 base_T_cam}
    (default: each view's chain pose). ``depths``: view -> (h, w) depth (NaN where none). ``per_pair``:
    also "pair_median_mm" {(a, b): median mm of that pair's samples}."""
    poses = poses or {v: dv.chain_T_cam for v, dv in views.items()}
    pts = {v: camera_points(depths[v], rays[v]) for v in depths}
    nrm = {v: normals(p) for v, p in pts.items()}
    samples = []
    pairs = 0
    by_pair = {}
    for a, nbrs in neighbours.items():
        if a not in depths:
            continue
        pa = pts[a][::SAMPLE_STRIDE, ::SAMPLE_STRIDE].reshape(-1, 3)
        pa = pa[np.isfinite(pa[:, 2])]
        for b in nbrs:
            if b not in depths:
                continue
            T = np.linalg.inv(poses[b]) @ poses[a]  # b <- a
            q = pa @ T[:3, :3].T + T[:3, 3]
            K = views[b].K
            w, h = views[b].size
            ok = q[:, 2] > 1e-3
            uv = np.round(q[ok, :2] / q[ok, 2:3] @ K[:2, :2].T + K[:2, 2]).astype(int)
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            qa, uv = q[ok][inside], uv[inside]
            pb, nb = pts[b][uv[:, 1], uv[:, 0]], nrm[b][uv[:, 1], uv[:, 0]]
            good = np.isfinite(pb[:, 2]) & np.isfinite(nb[:, 0])
            good[good] &= np.abs(qa[good, 2] - pb[good, 2]) < OCCLUSION_REL * pb[good, 2]
            if good.sum() < 50:
                continue
            samples.append(np.abs(np.sum((qa[good] - pb[good]) * nb[good], 1)))
            by_pair[(a, b)] = float(np.median(samples[-1])) * 1e3
            pairs += 1
    extra = {"pair_median_mm": by_pair} if per_pair else {}
    if not samples:
        return {"median_mm": None, "p90_mm": None, "samples": 0, "pairs": 0, **extra}
    d = np.concatenate(samples) * 1e3
    return {"median_mm": float(np.median(d)), "p90_mm": float(np.percentile(d, 90)), "samples": int(len(d)),
            "pairs": pairs, **extra}


def perturbed(ee_T_cam: np.ndarray, axis: int, translation_mm: float = 0.0, rotation_deg: float = 0.0) -> np.ndarray:
    """ee_T_cam moved by ``translation_mm`` along, or rotated by ``rotation_deg`` about, the ee frame's
    ``axis`` (0, 1, 2: x, y, z) at the camera's centre."""
    import gtsam

    e = np.zeros(3)
    e[axis] = 1.0
    T = ee_T_cam.copy()
    T[:3, 3] += translation_mm * 1e-3 * e
    T[:3, :3] = gtsam.Rot3.Expmap(np.radians(rotation_deg) * e).matrix() @ T[:3, :3]
    return T
