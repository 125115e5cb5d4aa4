"""Simulator: a textured tabletop raycast on the CPU, eye-in-hand trajectories for rigs of
1-3 cameras, and foundation-model-like predictions, written as ``calib3r-dataset/1``.

The predictions mimic what MASt3R-style networks hand over: per-view depth in an
unknown scale, a smooth low-frequency relative distortion (1-2 %), depth smeared
across object edges (with lower confidence there), pixel noise on the matches and a
fraction of gross outlier matches, on a sparse co-visibility graph.
"""

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import gtsam
import numpy as np
import open3d as o3d
import yaml
from scipy import ndimage
from tqdm import tqdm

from calib3r_graph.io.dataset import Camera, pose_to_dict, write_dataset_yaml, write_robot_poses
from calib3r_graph.io.output import atomic_path, atomic_write_text, staged_directory
from calib3r_graph.io.predictions import PairMatches, ViewPrediction, save_predictions, view_id

log = logging.getLogger(__name__)


@dataclass
class SimOptions:
    seed: int = 0
    frames: int = 12
    cameras: int = 1
    width: int = 640
    height: int = 480
    images: bool = True
    pattern: bool = False
    prediction_downsample: int = 2  # the network's grid is the image grid / this
    robot_noise_mm: float = 0.2
    robot_noise_deg: float = 0.02
    depth_distortion: float = 0.015  # peak relative smooth depth error
    depth_noise: float = 0.002  # relative per-pixel depth noise
    match_noise_px: float = 0.5  # on the network grid
    outlier_fraction: float = 0.04
    matches_per_pair: int = 2000
    neighbours: int = 4  # co-visibility: top-k neighbours per view
    unit: str = "m"
    trajectory: str = "hemisphere"  # or "orbit" (orbit_trajectory: one distance, the scale unobservable)


# Mounts of up to three cameras on the flange (ee_T_cam): different offsets and tilts,
# all looking roughly along the flange's z axis.
MOUNTS = [
    ((0.0, 0.0, 0.0), (0.04, -0.03, 0.09)),
    ((0.0, -0.25, 0.05), (-0.06, 0.05, 0.07)),
    ((0.22, 0.1, -0.1), (0.07, 0.06, 0.05)),
]
INTRINSICS = [(520.0, 520.0), (600.0, 595.0), (450.0, 455.0)]


def mount_pose(j: int, rng) -> gtsam.Pose3:
    rpy, t = MOUNTS[j]
    # The flange's z axis points out of the tool; a camera on it looks roughly along it,
    # rotated 90 degrees about z so the ee and cam axes differ.
    base = gtsam.Rot3.Rz(np.pi / 2)
    jitter = gtsam.Rot3.Expmap(rng.normal(size=3) * 0.02)
    R = base.compose(gtsam.Rot3.RzRyRx(*rpy)).compose(jitter)
    return gtsam.Pose3(R, np.array(t) + rng.normal(size=3) * 0.003)


def camera_for(j: int, opt: SimOptions) -> Camera:
    fx, fy = INTRINSICS[j]
    s = opt.width / 640.0
    return Camera(f"cam{j}", "PINHOLE", opt.width, opt.height,
                  (fx * s, fy * s, (opt.width - 1) / 2 + 3.0 * s, (opt.height - 1) / 2 - 2.0 * s), 0.001)


class Scene:
    """Table, objects and floor in the robot base frame, with solid procedural textures."""

    TABLE_TOP_Z = 0.0
    TABLE_CENTRE = np.array([0.55, 0.0])

    def __init__(self, rng, pattern: dict | None):
        self.scene = o3d.t.geometry.RaycastingScene()
        self.pattern = pattern
        cx, cy = self.TABLE_CENTRE
        self.board_origin = np.array([cx - 0.17, cy - 0.14, self.TABLE_TOP_Z + 1e-4])
        meshes = [self._box((1.4, 1.0, 0.04), (cx, cy, self.TABLE_TOP_Z - 0.02)),  # table top
                  self._box((4.0, 4.0, 0.02), (cx, cy, -0.76)),  # floor
                  self._box((4.0, 0.05, 1.6), (cx, cy + 0.9, 0.0))]  # a wall behind the table
        for _ in range(7):
            x, y = self.TABLE_CENTRE + rng.uniform([-0.45, -0.35], [0.45, 0.35])
            if pattern and abs(x - cx) < 0.25 and abs(y - cy + 0.02) < 0.2:
                continue  # keep the board free
            kind, h = rng.integers(3), rng.uniform(0.04, 0.18)
            if kind == 0:
                m = o3d.geometry.TriangleMesh.create_box(*rng.uniform(0.05, 0.14, 2), h)
                m.translate(-m.get_center() + np.array([x, y, h / 2]))
                m.rotate(o3d.geometry.get_rotation_matrix_from_xyz((0, 0, rng.uniform(0, np.pi))))
            elif kind == 1:
                m = o3d.geometry.TriangleMesh.create_cylinder(rng.uniform(0.03, 0.06), h, 32)
                m.translate([x, y, h / 2])
            else:
                r = rng.uniform(0.03, 0.07)
                m = o3d.geometry.TriangleMesh.create_sphere(r, 24)
                m.translate([x, y, r])
            meshes.append(m)
        for m in meshes:
            self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
        # Solid texture: a sum of random plane waves per colour channel (multi-scale, SIFT-friendly).
        n = 24
        dirs = rng.normal(size=(3, n, 3))
        dirs /= np.linalg.norm(dirs, axis=2, keepdims=True)
        self.wave_k = dirs * rng.uniform(15, 160, size=(3, n, 1))
        self.wave_phase = rng.uniform(0, 2 * np.pi, size=(3, n))

    @staticmethod
    def _box(size, centre):
        m = o3d.geometry.TriangleMesh.create_box(*size)
        m.translate(np.array(centre) - np.array(size) / 2)
        return m

    def raycast(self, K, base_T_cam: gtsam.Pose3, width, height):
        """z-depth (h, w) (inf where nothing is hit), world points and normals, geometry ids."""
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        rays_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T  # z = 1
        R, t = base_T_cam.rotation().matrix(), base_T_cam.translation()
        dirs = rays_cam @ R.T
        rays = np.concatenate([np.broadcast_to(t, dirs.shape), dirs], -1).astype(np.float32)
        hit = self.scene.cast_rays(o3d.core.Tensor(rays))
        depth = hit["t_hit"].numpy().astype(np.float64)  # along K^-1[u,v,1]: equals z-depth
        points = t + dirs * np.where(np.isfinite(depth), depth, 0)[..., None]
        return depth, points, hit["primitive_normals"].numpy(), hit["geometry_ids"].numpy()

    def colour(self, points, normals, base_T_cam: gtsam.Pose3):
        """RGB float [0, 1] of world points: solid texture, checkerboard, Lambert shading."""
        phase = np.einsum("...d,cnd->...cn", points, self.wave_k) + self.wave_phase
        tex = 0.5 + 0.5 * np.tanh(1.5 * np.cos(phase).sum(-1) / np.sqrt(self.wave_k.shape[1]))
        if self.pattern:
            cols, rows = self.pattern["inner_corners"]
            sq = self.pattern["square_size"]
            local = (points - self.board_origin)[..., :2] / sq
            on_table = np.abs(points[..., 2] - self.TABLE_TOP_Z) < 1e-3
            border = 0.8
            inside = on_table & (local[..., 0] > -border) & (local[..., 0] < cols + 1 + border) & \
                (local[..., 1] > -border) & (local[..., 1] < rows + 1 + border)
            board = ((np.floor(local[..., 0]) + np.floor(local[..., 1])) % 2 == 0).astype(float)
            squares = inside & (local[..., 0] >= 0) & (local[..., 0] < cols + 1) & (local[..., 1] >= 0) & (local[..., 1] < rows + 1)
            white = np.where(squares, 0.05 + 0.85 * board, 0.9)
            tex = np.where(inside[..., None], white[..., None], tex)
        light = np.array([0.3, -0.4, 0.87])
        light /= np.linalg.norm(light)
        shade = 0.55 + 0.45 * np.abs(normals @ light)
        return np.clip(tex * shade[..., None], 0, 1)


def trajectory(rng, n: int, ee_T_cam0: gtsam.Pose3) -> list:
    """base_T_ee for n frames: cam0 looks at the table from a hemisphere, with varied roll."""
    poses = []
    centre = np.r_[Scene.TABLE_CENTRE, 0.0]
    for i in range(n):
        az = np.deg2rad(rng.uniform(-70, 70)) + np.pi  # from the robot's side of the table
        el = np.deg2rad(rng.uniform(40, 75))
        dist = rng.uniform(0.5, 0.75)
        eye = centre + dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        target = centre + np.r_[rng.uniform(-0.12, 0.12, 2), 0.0]
        z = target - eye
        z /= np.linalg.norm(z)
        down = np.array([0.0, 0.0, -1.0])
        y = down - (down @ z) * z
        y /= np.linalg.norm(y)
        R = np.stack([np.cross(y, z), y, z], axis=1)
        roll = gtsam.Rot3.Rz(np.deg2rad(rng.uniform(-35, 35)))
        base_T_cam0 = gtsam.Pose3(gtsam.Rot3(R).compose(roll), eye)
        poses.append(base_T_cam0.compose(ee_T_cam0.inverse()))
    return poses


# rwhe_kuka_2's orbit (its RobotPosesVec.txt): the flange's viewing axis passes within 2 mm (median,
# 7.5 mm at most) of one point, 0.396-0.421 m away, from directions a median 32 degrees apart.
ORBIT_DISTANCE_M = 0.41
ORBIT_DISTANCE_SPREAD = 0.03  # relative, peak to peak
ORBIT_AIM_JITTER_M = 0.003
ORBIT_SPREAD_DEG = 35.0  # the viewing directions' cone half-angle


def orbit_trajectory(rng, n: int, ee_T_cam0: gtsam.Pose3, distance: float = ORBIT_DISTANCE_M) -> list:
    """base_T_ee for n frames on an orbit like rwhe_kuka_2's: cam0 circles the table's centre at one
    distance, looking at it, from directions within a cone about a view from the robot's side at 60
    degrees elevation, with varied roll. On such an orbit every optical axis passes (nearly) through
    one point, so the metric scale and ee_T_cam along the optical axis trade against each other."""
    centre = np.r_[Scene.TABLE_CENTRE, 0.0]
    el, az = np.radians(60.0), np.pi
    mean = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    poses = []
    for _ in range(n):
        axis = np.cross(mean, rng.normal(size=3))
        tilt = gtsam.Rot3.AxisAngle(gtsam.Unit3(axis).point3(), np.radians(ORBIT_SPREAD_DEG) * np.sqrt(rng.uniform()))
        d = distance * (1 + ORBIT_DISTANCE_SPREAD * rng.uniform(-0.5, 0.5))
        target = centre + rng.normal(size=3) * ORBIT_AIM_JITTER_M
        eye = target + d * (tilt.matrix() @ mean)
        poses.append(look_at(eye, target, rng.uniform(-35, 35)).compose(ee_T_cam0.inverse()))
    return poses


def look_at(eye, target, roll_deg: float) -> gtsam.Pose3:
    """base_T_cam of a camera at ``eye`` whose z axis points at ``target``, its image's y axis towards
    the base's -z, then rolled by ``roll_deg`` about its z."""
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    down = np.array([0.0, 0.0, -1.0])
    y = down - (down @ z) * z
    y /= np.linalg.norm(y)
    R = np.stack([np.cross(y, z), y, z], axis=1)
    return gtsam.Pose3(gtsam.Rot3(R).compose(gtsam.Rot3.Rz(np.deg2rad(roll_deg))), np.asarray(eye, float))


def render_rgb(scene: Scene, cam: Camera, base_T_cam: gtsam.Pose3, rng):
    """(HxWx3 uint8 RGB image with 1.5 grey levels of noise, z-depth in m (inf where nothing is hit))."""
    depth, pts, normals, _ = scene.raycast(cam.K, base_T_cam, cam.width, cam.height)
    rgb = scene.colour(pts, normals, base_T_cam)
    rgb = np.clip(rgb * 255 + rng.normal(scale=1.5, size=rgb.shape), 0, 255).astype(np.uint8)
    rgb[~np.isfinite(depth)] = 0
    return rgb, depth


def render_poses(dataset_dir, base_T_ee: dict, seed: int = 0) -> dict:
    """{frame: {camera: HxWx3 uint8 RGB}}: the scene of a simulated dataset (its ground_truth.yaml)
    seen by each of its cameras (their true mounts) from the given true flange poses (gtsam.Pose3 or
    4x4), rendered as ``simulate`` renders its images. For a live session's proposed poses."""
    from calib3r_graph.io.dataset import load_dataset, pose_from_dict

    root = Path(dataset_dir)
    gt = yaml.safe_load((root / "ground_truth.yaml").read_text())
    scene = scene_from_simulation(gt["simulation"])
    cams = load_dataset(root).cameras
    rng = np.random.default_rng(seed)
    out = {}
    for f, E in base_T_ee.items():
        E = E if isinstance(E, gtsam.Pose3) else gtsam.Pose3(np.asarray(E, float))
        out[f] = {c: render_rgb(scene, cam, E.compose(pose_from_dict(gt["hand_eye"][c])), rng)[0]
                  for c, cam in cams.items()}
    return out


def smooth_distortion(rng, h, w, amplitude) -> np.ndarray:
    """A smooth relative depth error field (h, w) with peak |value| = amplitude."""
    y, x = np.mgrid[0:h, 0:w]
    x, y = 2 * x / (w - 1) - 1, 2 * y / (h - 1) - 1
    basis = [x, y, x * x, x * y, y * y, np.sin(2.1 * x + rng.uniform(0, 6)), np.cos(1.7 * y + rng.uniform(0, 6))]
    field = sum(rng.normal() * b for b in basis)
    return amplitude * field / np.abs(field).max()


def predict_view(rng, depth_true, opt: SimOptions, scale_units_per_m: float):
    """Network-like depth and confidence from true z-depth (inf = no hit)."""
    h, w = depth_true.shape
    valid = np.isfinite(depth_true)
    d = np.where(valid, depth_true, 0.0)
    # Edges: relative depth jumps between neighbours, widened by a few pixels, get smeared.
    jump = np.zeros_like(d, dtype=bool)
    rel = np.abs(np.diff(d, axis=1)) / np.maximum(d[:, 1:], 1e-6)
    jump[:, 1:] |= rel > 0.03
    jump[:, :-1] |= rel > 0.03
    rel = np.abs(np.diff(d, axis=0)) / np.maximum(d[1:], 1e-6)
    jump[1:] |= rel > 0.03
    jump[:-1] |= rel > 0.03
    band = ndimage.binary_dilation(jump, iterations=2) & valid
    blurred = ndimage.gaussian_filter(d, 2.0)
    d = np.where(band, blurred, d)
    d = d * (1 + smooth_distortion(rng, h, w, opt.depth_distortion))
    d = d * (1 + opt.depth_noise * rng.normal(size=d.shape))
    conf = np.where(band, 0.3, 1.0) * rng.uniform(0.8, 1.2, size=d.shape)
    conf = np.where(valid, conf, 0.0).astype(np.float32)
    return np.where(valid, d * scale_units_per_m, 0.0).astype(np.float32), conf


def project(K, cam_T_base: gtsam.Pose3, pts):
    q = pts @ cam_T_base.rotation().matrix().T + cam_T_base.translation()
    uv = q[:, :2] / q[:, 2:3] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
    return uv, q[:, 2]


def simulate_matches(rng, views, a, b, n, opt: SimOptions):
    """Matches from view a to b via the true geometry, with pixel noise and outliers."""
    va, vb = views[a], views[b]
    h, w = va["depth"].shape
    valid = np.flatnonzero(np.isfinite(va["depth"]).ravel())
    if len(valid) == 0:
        return None
    idx = rng.choice(valid, size=min(len(valid), 6 * n), replace=False)
    uv_a = np.stack([idx % w, idx // w], 1).astype(np.float64)
    pts = va["points"].reshape(-1, 3)[idx]
    uv_b, z_b = project(vb["K"], vb["pose"].inverse(), pts)
    ui, vi = np.round(uv_b[:, 0]).astype(int), np.round(uv_b[:, 1]).astype(int)
    inside = (z_b > 0) & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    vis = np.zeros(len(idx), bool)
    vis[inside] = np.abs(vb["depth"][vi[inside], ui[inside]] - z_b[inside]) < 0.01 * z_b[inside]
    # Stay clear of the borders so noisy matches keep inside the grid.
    vis &= (uv_b[:, 0] > 1) & (uv_b[:, 0] < w - 2) & (uv_b[:, 1] > 1) & (uv_b[:, 1] < h - 2)
    keep = np.flatnonzero(vis)[:n]
    if len(keep) < 30:
        return None
    uv_a, uv_b = uv_a[keep], uv_b[keep] + rng.normal(scale=opt.match_noise_px, size=(len(keep), 2))
    conf = np.minimum(va["conf"].ravel()[idx[keep]], 1.0) * rng.uniform(0.7, 1.0, len(keep))
    n_out = int(round(opt.outlier_fraction * len(keep)))
    out = rng.choice(len(keep), n_out, replace=False)
    uv_b[out] = rng.uniform([2, 2], [w - 3, h - 3], size=(n_out, 2))
    return PairMatches(a, b, uv_a, uv_b, conf)


def overlap(views, a, b, rng) -> float:
    va, vb = views[a], views[b]
    valid = np.flatnonzero(np.isfinite(va["depth"]).ravel())
    idx = rng.choice(valid, size=min(400, len(valid)), replace=False)
    uv, z = project(vb["K"], vb["pose"].inverse(), va["points"].reshape(-1, 3)[idx])
    h, w = vb["depth"].shape
    return float(np.mean((z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)))


def simulate(out_dir, opt: SimOptions, progress: bool = True) -> Path:
    """Write a complete dataset (with ground_truth.yaml and predictions/sim) to ``out_dir``."""
    if not 1 <= opt.cameras <= len(MOUNTS):
        raise ValueError(f"--cameras must be 1..{len(MOUNTS)}")
    rng = np.random.default_rng(opt.seed)
    pattern = _board(opt)
    scene = Scene(rng, pattern)  # first from the seed, so scene_from_simulation rebuilds it
    cams = [camera_for(j, opt) for j in range(opt.cameras)]
    mounts = [mount_pose(j, rng) for j in range(opt.cameras)]
    if opt.trajectory not in ("hemisphere", "orbit"):
        raise ValueError(f"trajectory must be hemisphere or orbit, not {opt.trajectory!r}")
    true_ee = (orbit_trajectory if opt.trajectory == "orbit" else trajectory)(rng, opt.frames, mounts[0])
    frames = [f"{i:04d}" for i in range(opt.frames)]
    noise = lambda: np.r_[rng.normal(size=3) * np.deg2rad(opt.robot_noise_deg), rng.normal(size=3) * opt.robot_noise_mm * 1e-3]
    measured_ee = {f: E.compose(gtsam.Pose3.Expmap(noise())) for f, E in zip(frames, true_ee)}

    out_dir = Path(out_dir)
    ds = opt.prediction_downsample
    views, gt_views = {}, {}
    with staged_directory(out_dir) as stage:
        it = [(f, E, j) for f, E in zip(frames, true_ee) for j in range(opt.cameras)]
        for f, E, j in tqdm(it, desc="render", disable=None if progress else True, leave=False):
            cam, pose = cams[j], E.compose(mounts[j])
            vid = view_id(cam.name, f)
            if opt.images:
                rgb, depth = render_rgb(scene, cam, pose, rng)
                _write_png(stage / "images" / cam.name / f"{f}.png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
                depth_mm = np.where(np.isfinite(depth), np.round(depth * 1000), 0).clip(0, 65535).astype(np.uint16)
                _write_png(stage / "depth" / cam.name / f"{f}.png", depth_mm)
            # The network's grid: image resized by 1/ds (OpenCV pixel-centre convention).
            K = cam.K.copy()
            K[:2] /= ds
            K[0, 2] = (cam.K[0, 2] + 0.5) / ds - 0.5
            K[1, 2] = (cam.K[1, 2] + 0.5) / ds - 0.5
            gw, gh = cam.width // ds, cam.height // ds
            depth, pts, _, _ = scene.raycast(K, pose, gw, gh)
            units_per_m = float(np.exp(rng.uniform(np.log(0.3), np.log(3.0))))
            d_pred, conf = predict_view(rng, depth, opt, units_per_m)
            views[vid] = {"depth": depth, "points": pts, "K": K, "pose": pose, "conf": conf, "pred": d_pred}
            gt_views[vid] = {"base_T_cam": pose_to_dict(pose), "metres_per_depth_unit": 1.0 / units_per_m}

        ids = list(views)
        edges = set()
        for a in ids:
            scores = sorted(((overlap(views, a, b, rng), b) for b in ids if b != a), reverse=True)
            for s, b in scores[:opt.neighbours]:
                if s > 0.2:
                    edges.add(tuple(sorted((a, b))))
            # Rigs: every camera at the same frame is a neighbour when they overlap.
            for s, b in scores:
                if b.split("/")[1] == a.split("/")[1] and s > 0.1:
                    edges.add(tuple(sorted((a, b))))
        pairs = []
        for a, b in tqdm(sorted(edges), desc="matches", disable=None if progress else True, leave=False):
            p = simulate_matches(rng, views, a, b, opt.matches_per_pair, opt)
            if p is not None:
                pairs.append(p)
        pred_views = {v: ViewPrediction(d["pred"], d["conf"], d["K"]) for v, d in views.items()}
        save_predictions(stage, "sim", pred_views, pairs,
                         {"source": "calib3r-graph simulate", "metric_depth": False,
                          "depth_distortion": opt.depth_distortion, "outlier_fraction": opt.outlier_fraction,
                          "match_noise_px": opt.match_noise_px})
        write_dataset_yaml(stage, cams, unit=opt.unit, pattern=pattern)
        write_robot_poses(stage / "robot_poses.csv", measured_ee, unit=opt.unit)
        gt = {"hand_eye": {c.name: pose_to_dict(m) for c, m in zip(cams, mounts)},
              "base_T_ee_true": {f: pose_to_dict(E) for f, E in zip(frames, true_ee)},
              "views": gt_views,
              "simulation": {k: v for k, v in vars(opt).items()}}
        if pattern:
            gt["pattern_origin_in_base"] = [float(x) for x in scene.board_origin + np.array([1, 1, 0]) * pattern["square_size"]]
        atomic_write_text(stage / "ground_truth.yaml", yaml.safe_dump(gt, sort_keys=False))
    return out_dir


def _board(opt: SimOptions) -> dict | None:
    return {"type": "checkerboard", "inner_corners": [9, 6], "square_size": 0.03} if opt.pattern else None


def scene_from_simulation(simulation: dict) -> Scene:
    """The true scene of a simulated dataset, rebuilt from its ground_truth.yaml ``simulation`` entry
    (the options it was made with): ``simulate`` builds the scene first from the seeded generator."""
    fields = SimOptions.__dataclass_fields__
    opt = SimOptions(**{k: v for k, v in simulation.items() if k in fields})
    return Scene(np.random.default_rng(opt.seed), _board(opt))


def _write_png(path: Path, img):
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img):
            raise OSError(f"cannot encode {path}")
