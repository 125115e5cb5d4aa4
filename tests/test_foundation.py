"""Foundation-model converters on files with the real keys and shapes (VGGT predictions.npz,
DUSt3R/MASt3R exports), made from the simulator's truth on the networks' own grids."""

import cv2
import gtsam
import numpy as np
import pytest

from calib3r_graph.errors import InputError
from calib3r_graph.evaluation.evaluate import hand_eye_errors
from calib3r_graph.frontends.foundation import convert, dust3r_grid, grid_intrinsics, vggt_grid
from calib3r_graph.io.dataset import load_dataset, load_ground_truth, pose_from_dict
from calib3r_graph.io.predictions import load_predictions
from calib3r_graph.solver.solve import SolveOptions, solve


def test_network_grids_match_the_models_preprocessing():
    assert vggt_grid(640, 480)[4:] == (518, 392)  # width 518, height rounded to a multiple of 14
    assert vggt_grid(1928, 1208)[4:] == (518, 322)
    assert vggt_grid(480, 640, "pad")[4:] == (518, 518)
    assert vggt_grid(640, 1200, "crop")[4:] == (518, 518)  # 518 x 966 centre-cropped
    assert dust3r_grid(640, 480)[4:] == (512, 384)
    assert dust3r_grid(1928, 1208)[4:] == (512, 320)  # 512 x 321, cropped to multiples of 16
    # The image centre maps to the grid centre (pixel-centre convention).
    K = np.array([[500.0, 0, 319.5], [0, 500, 239.5], [0, 0, 1]])
    Kg = grid_intrinsics(K, dust3r_grid(640, 480))
    assert Kg[0, 2] == pytest.approx(255.5) and Kg[1, 2] == pytest.approx(191.5) and Kg[0, 0] == pytest.approx(400)


def export_like(kind, root, rng):
    """A model export made from the simulator: the grid's depth (with the simulated distortion),
    one consistent unknown scale and an arbitrary world frame. The model's intrinsics are
    those of its grid: a real network's depth, poses and focal explain the images together,
    so its correspondences (pointmaps) are consistent with its own K."""
    ds = load_dataset(root)
    gt = load_ground_truth(root)
    preds = load_predictions(root, "sim", ds.cameras, set(ds.frames))
    scale = 0.37
    world_T_base = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3))
    names, depth, conf, cam2w, K_model = [], [], [], [], []
    for vid, vp in sorted(preds.views.items()):
        cam = ds.cameras[vid.split("/")[0]]
        grid = vggt_grid(cam.width, cam.height) if kind == "vggt" else dust3r_grid(cam.width, cam.height)
        sx, sy, ox, oy, w, h = grid
        u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        uo, vo = (u + 0.5 + ox) / sx - 0.5, (v + 0.5 + oy) / sy - 0.5  # image pixel
        K_sim, K_img = vp.K, cam.K
        us = (uo - K_img[0, 2]) / K_img[0, 0] * K_sim[0, 0] + K_sim[0, 2]  # sim grid pixel
        vs = (vo - K_img[1, 2]) / K_img[1, 1] * K_sim[1, 1] + K_sim[1, 2]
        d = cv2.remap(vp.depth, us.astype(np.float32), vs.astype(np.float32), cv2.INTER_NEAREST)
        c = cv2.remap(vp.conf, us.astype(np.float32), vs.astype(np.float32), cv2.INTER_NEAREST)
        depth.append(d * gt["views"][vid]["metres_per_depth_unit"] * scale)
        conf.append(1.0 + 4.0 * c)
        T = world_T_base.compose(pose_from_dict(gt["views"][vid]["base_T_cam"]))
        cam2w.append(np.vstack([np.c_[T.rotation().matrix(), T.translation() * scale], [0, 0, 0, 1]]))
        K_model.append(grid_intrinsics(cam.K, grid))
        names.append(f"/gpu/box/images/{vid}.png")
    depth, conf, cam2w, K_model = map(np.array, (depth, conf, cam2w, K_model))
    path = root / f"{kind}_export.npz"
    if kind == "vggt":
        S, H, W = depth.shape
        np.savez(path, depth=depth[..., None].astype(np.float32), depth_conf=conf.astype(np.float32),
                 extrinsic=np.linalg.inv(cam2w)[:, :3].astype(np.float32), intrinsic=K_model.astype(np.float32),
                 pose_enc=np.zeros((S, 9), np.float32), world_points=np.zeros((S, H, W, 3), np.float32),
                 world_points_conf=conf.astype(np.float32), images=np.zeros((S, 3, H, W), np.float32),
                 image_names=np.array(names))
    else:
        np.savez(path, image_names=np.array(names), depthmaps=depth.astype(np.float32), conf=conf.astype(np.float32),
                 cam2w=cam2w.astype(np.float32), focals=K_model[:, 0, 0].astype(np.float32),
                 pp=K_model[:, :2, 2].astype(np.float32))
    return path


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["vggt", "dust3r"])
def test_converted_export_solves_accurately(simulated, tmp_path, kind):
    import shutil

    root = tmp_path / "d"
    shutil.copytree(simulated(seed=41, frames=10), root)
    path = export_like(kind, root, np.random.default_rng(0))
    ds = load_dataset(root)
    name = convert(kind, path, ds)
    preds = load_predictions(root, name, ds.cameras, set(ds.frames))
    assert len(preds.views) == 10 and len(preds.pairs) >= 10
    sol = solve(ds, preds, SolveOptions())
    e = hand_eye_errors(sol.ee_T_cam, load_ground_truth(root))["cam0"]
    assert e["e_t_m"] < 2e-3 and np.degrees(e["e_theta_rad"]) < 0.15, e


def test_wrong_grid_is_a_clear_error(simulated, tmp_path):
    import shutil

    root = tmp_path / "d"
    shutil.copytree(simulated(seed=41, frames=10), root)
    path = export_like("vggt", root, np.random.default_rng(0))
    with pytest.raises(InputError, match="wrong --vggt-mode"):
        convert("vggt", path, load_dataset(root), vggt_mode="pad")
    z = dict(np.load(path))
    del z["depth_conf"]
    np.savez(path, **z)
    with pytest.raises(InputError, match="depth_conf"):
        convert("vggt", path, load_dataset(root))


def test_pairwise_pointmaps_are_aggregated_by_confidence():
    from calib3r_graph.frontends.common import aggregate_pointmaps

    d = np.array([[[1.0, 2.0]], [[3.0, 0.0]], [[np.nan, 4.0]]])  # 3 pairwise predictions of a 1x2 view
    c = np.array([[[1.0, 1.0]], [[3.0, 5.0]], [[2.0, 1.0]]])
    depth, conf = aggregate_pointmaps(d, c)
    assert depth[0, 0] == pytest.approx((1 * 1 + 3 * 3) / 4)  # the NaN prediction carries no weight
    assert depth[0, 1] == pytest.approx((2 * 1 + 4 * 1) / 2)  # nor does the zero depth
    assert conf[0, 0] == pytest.approx(4 / 3) and conf[0, 1] == pytest.approx(2 / 3)


@pytest.mark.slow
def test_dust3r_export_with_pairwise_predictions(simulated, tmp_path):
    """An export with two pairwise predictions per view, one of them 5 % off with low confidence."""
    import shutil

    root = tmp_path / "d"
    shutil.copytree(simulated(seed=41, frames=10), root)
    path = export_like("dust3r", root, np.random.default_rng(0))
    z = dict(np.load(path))
    z["depthmaps"] = np.stack([z["depthmaps"], z["depthmaps"] * 1.05], axis=1)
    z["conf"] = np.stack([z["conf"] * 99, z["conf"]], axis=1)
    np.savez(path, **z)
    ds = load_dataset(root)
    preds = load_predictions(root, convert("dust3r", path, ds), ds.cameras, set(ds.frames))
    sol = solve(ds, preds, SolveOptions())
    e = hand_eye_errors(sol.ee_T_cam, load_ground_truth(root))["cam0"]
    assert e["e_t_m"] < 2e-3 and np.degrees(e["e_theta_rad"]) < 0.15, e
