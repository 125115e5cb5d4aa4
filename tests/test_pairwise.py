"""The pairwise RGB frontend (calib3r_graph/frontends/pairwise.py): its per-view scale alignment
and robot checks on constructed pairs, a rendered scene solved from 8 images, a view it cannot
use, a two-camera rig, and 8 real images of rwhe_kuka_1 against the full recording."""

import shutil

import cv2
import gtsam
import numpy as np
import pytest

from calib3r_graph.cli import main
from calib3r_graph.evaluation.consistency import in_sigmas
from calib3r_graph.evaluation.evaluate import hand_eye_errors
from calib3r_graph.frontends.pairwise import (Features, PairGeometry, PairwiseOptions, pairwise_predictions,
                                              robot_consistent, view_depths)
from calib3r_graph.geometry import pose_error
from calib3r_graph.io.dataset import load_dataset, load_ground_truth, subset_dataset
from calib3r_graph.io.predictions import load_predictions
from calib3r_graph.io.results import uncertainty_report
from calib3r_graph.solver.graph import NoiseOptions
from calib3r_graph.solver.solve import SolveOptions, solve
from tests.conftest import SHARED

REAL = SHARED / "real"
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason="../shared/real (public recordings) is not beside this checkout")


def _solve(ds, preds):
    return solve(ds, preds, SolveOptions(noise=NoiseOptions(pixel_sigma_px=preds.info["match_noise_px"]),
                                         progress=False))


def test_each_pairs_scale_is_aligned_to_the_view_and_an_inconsistent_pair_gives_no_depth():
    """Three pairs see overlapping keypoints of view v, each triangulated in its own unit (its
    baseline): one depth map in one unit comes out. A fourth pair whose depths do not follow the
    others' (a wrong two-view geometry) is left out of v's depth."""
    rng = np.random.default_rng(0)
    n = 300
    z = rng.uniform(1.0, 3.0, n)
    feats = Features(rng.uniform(0, 100, (n, 2)), np.zeros((n, 128), np.float32), np.arange(n))
    geoms = {}
    for k, (scale, lo, hi) in enumerate([(0.3, 0, 150), (2.0, 100, 250), (7.0, 200, 300), (1.0, 0, 300)]):
        idx = np.arange(lo, hi)
        d = z[idx] * scale * (1 + 0.001 * rng.standard_normal(len(idx)))
        if k == 3:
            d = rng.uniform(1.0, 3.0, len(idx))  # unrelated to the scene
        other = np.arange(len(idx))
        # view v is the pair's second view for k = 1: the alignment must not care
        ab = ("cam0/v", f"cam0/w{k}") if k != 1 else (f"cam0/w{k}", "cam0/v")
        ia, ib, da, db = (idx, other, d, d) if k != 1 else (other, idx, d, d)
        geoms[ab] = PairGeometry(*ab, ia, ib, da, db, np.full(len(idx), np.radians(10)), np.ones(len(idx)),
                                 np.eye(3), np.array([1.0, 0, 0]))
    ids, depth, conf, scales = view_depths("cam0/v", feats, geoms, PairwiseOptions())
    assert len(ids) == n and set(scales) == set(list(geoms)[:3])
    ratio = depth / z[ids]
    assert np.std(ratio) / np.mean(ratio) < 0.002
    # eq. 1's conf is the mean over the pairs that gave depth: keypoints seen by two pairs count more
    assert conf[(ids >= 100) & (ids < 150)].min() > conf[ids < 100].max()


def test_pairs_that_disagree_with_the_robots_rotation_are_dropped():
    """The camera's relative rotation angle must equal the flange's (for any hand-eye rotation),
    and the rotation itself must agree with a rough hand-eye rotation found from the pairs."""
    rng = np.random.default_rng(1)
    X = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.3, -0.2, 1.2), np.array([0.05, -0.02, 0.1]))
    frames = [f"{i:04d}" for i in range(6)]
    base_T_ee = {f: gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.3, 3)), rng.normal(0, 0.2, 3)) for f in frames}
    geoms = {}
    for i, a in enumerate(frames):
        for b in frames[i + 1:]:
            B = X.inverse().compose(base_T_ee[a].between(base_T_ee[b])).compose(X)  # a_T_b
            R = B.rotation().matrix().T  # x_b = R x_a + t
            t = -R @ B.translation()
            geoms[(f"cam0/{a}", f"cam0/{b}")] = PairGeometry(f"cam0/{a}", f"cam0/{b}", *([np.zeros(0)] * 6), R,
                                                             t / np.linalg.norm(t))
    bad_angle, bad_axis, bad_t = ("cam0/0000", "cam0/0001"), ("cam0/0002", "cam0/0004"), ("cam0/0001", "cam0/0005")
    g = geoms[bad_angle]
    g.R = gtsam.Rot3.Expmap(np.array([0, 0, np.radians(4)])).matrix() @ g.R  # angle changes by ~4 degrees
    g = geoms[bad_axis]
    angle = np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(g.R)))
    axis = np.cross(gtsam.Rot3.Logmap(gtsam.Rot3(g.R)), [1.0, 0, 0])
    g.R = gtsam.Rot3.Expmap(angle * axis / np.linalg.norm(axis)).matrix()  # same angle, another axis
    g = geoms[bad_t]
    g.t = gtsam.Rot3.Expmap(np.array([0, np.radians(20), 0])).matrix() @ g.t
    kept, info = robot_consistent(geoms, base_T_ee, PairwiseOptions())
    assert set(geoms) - set(kept) == {bad_angle, bad_axis, bad_t}, info
    R_X = np.array(info["hand_eye"]["cam0"]["rotation"])
    assert np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(R_X.T @ X.rotation().matrix())))) < 0.01


@pytest.fixture(scope="module")
def rendered_rgb(tmp_path_factory):
    """8 rendered 320x240 images with robot poses: no depth, no predictions."""
    from calib3r_graph.simulate import SimOptions, simulate

    root = simulate(tmp_path_factory.mktemp("pw") / "d", SimOptions(seed=0, frames=8, width=320, height=240),
                    progress=False)
    shutil.rmtree(root / "predictions")
    shutil.rmtree(root / "depth", ignore_errors=True)
    return root


@pytest.mark.slow
def test_pairwise_frontend_solves_a_rendered_scene_from_8_images(rendered_rgb, tmp_path):
    """predict --frontend pairwise, then solve: within 3 mm / 0.2 deg of the truth (measured:
    0.6-1.0 mm, 0.04-0.07 deg over seeds 0-3)."""
    d = tmp_path / "d"
    shutil.copytree(rendered_rgb, d)
    assert main(["-q", "predict", str(d), "--frontend", "pairwise"]) == 0
    ds = load_dataset(d)
    preds = load_predictions(d, "pairwise", ds.cameras, set(ds.frames))
    assert preds.info["metric_depth"] is False and len(preds.views) == 8 and preds.info["unusable_views"] == []
    assert len(preds.pairs) >= 12 and min(len(p.uv_a) for p in preds.pairs) >= 20
    for v in preds.views.values():  # sparse depth: splats at keypoints, conf 0 elsewhere
        assert 0.001 < (v.depth > 0).mean() < 0.5 and np.all((v.conf > 0) == (v.depth > 0))
    e = hand_eye_errors(_solve(ds, preds).ee_T_cam, load_ground_truth(d))["cam0"]
    assert e["e_t_m"] <= 3e-3 and np.degrees(e["e_theta_rad"]) <= 0.2, e


@pytest.mark.slow
def test_a_view_the_frontend_cannot_use_is_named_and_the_rest_solve(rendered_rgb, tmp_path, caplog):
    d = tmp_path / "d"
    shutil.copytree(rendered_rgb, d)
    ds = load_dataset(d)
    blank = ds.image_path("cam0", ds.frames[3])
    cv2.imwrite(str(blank), np.full((240, 320, 3), 128, np.uint8))  # no texture: no features
    preds = pairwise_predictions(ds, progress=False)
    bad = f"cam0/{ds.frames[3]}"
    assert bad not in preds.views and preds.info["unusable_views"] == [bad] and len(preds.views) == 7
    assert any(bad in r.getMessage() and r.levelname == "WARNING" for r in caplog.records)
    e = hand_eye_errors(_solve(ds, preds).ee_T_cam, load_ground_truth(d))["cam0"]
    assert e["e_t_m"] <= 3e-3 and np.degrees(e["e_theta_rad"]) <= 0.2, e


@pytest.mark.slow
def test_a_two_camera_rig(tmp_path):
    """Two cameras on the flange: pairs across the cameras (a rig's same-frame pairs have a
    relative rotation the flange does not make) are kept without robot checks, and each camera's
    own pairs are checked against its own rough hand-eye. Within 3 mm / 0.2 deg of the truth
    (measured: 0.6 mm, 0.08 deg)."""
    from calib3r_graph.simulate import SimOptions, simulate

    root = simulate(tmp_path / "rig", SimOptions(seed=5, frames=8, cameras=2, width=320, height=240), progress=False)
    shutil.rmtree(root / "predictions")
    shutil.rmtree(root / "depth", ignore_errors=True)
    ds = load_dataset(root)
    preds = pairwise_predictions(ds, progress=False)
    assert len(preds.views) == 16
    assert any(p.view_a.split("/")[0] != p.view_b.split("/")[0] for p in preds.pairs)
    for e in hand_eye_errors(_solve(ds, preds).ee_T_cam, load_ground_truth(root)).values():
        assert e["e_t_m"] <= 3e-3 and np.degrees(e["e_theta_rad"]) <= 0.2, e


ISSUE_FRAMES = ["0001", "0005", "0014", "0017", "0020", "0023", "0026", "0029"]


@needs_real
@pytest.mark.slow
def test_eight_real_images_agree_with_the_full_recording(tmp_path):
    """The 8 frames of rwhe_kuka_1 on which COLMAP's mapper registered 2 images (issue 14): with
    the pairwise frontend every view is used and the result is within 3 mm / 0.2 deg of the full
    30-frame result (measured: 1.1-1.6 mm, 0.05 deg). Six poses whose noise-model sigma does not
    cover their error are covered once the jackknife runs (the default below 15 poses). Features and pair geometries of the full
    run are cached and re-used by the subset, as in bench/views_real.py (about 45 s on 2 cores)."""
    from calib3r_graph.importers import import_recording

    root = tmp_path / "rwhe"
    import_recording("rwhe", REAL / "rwhe_kuka_1", root, (28, 17), progress=False)
    ds = load_dataset(root)
    cache = tmp_path / "cache"
    full = _solve(ds, pairwise_predictions(ds, cache_dir=cache, progress=False))
    sub = subset_dataset(ds, ISSUE_FRAMES)
    preds = pairwise_predictions(sub, cache_dir=cache, progress=False)
    assert sorted(preds.views) == [f"cam0/{f}" for f in ISSUE_FRAMES]
    few = _solve(sub, preds)
    et, er = pose_error(few.ee_T_cam["cam0"], full.ee_T_cam["cam0"])
    assert et < 3e-3 and er < 0.2, (et, er)
    # Six poses of which the noise model alone is over-confident (bench/views_real.py, kuka_1 6-view
    # subset 10: 5.7 mm from the full result, mostly along ee z): its total covers the leave-one-pose-out
    # jackknife, which covers the difference (measured: 5.3 sigma without it, 1.3 with it).
    six = ["0009", "0010", "0013", "0018", "0027", "0029"]
    sub6 = subset_dataset(ds, six)
    preds6 = pairwise_predictions(sub6, cache_dir=cache, progress=False)
    ratios = {}
    for mode in ("never", "auto"):
        sol = solve(sub6, preds6, SolveOptions(noise=NoiseOptions(pixel_sigma_px=preds6.info["match_noise_px"]),
                                               progress=False, jackknife=mode))
        sig = uncertainty_report(sol.ee_T_cam["cam0"], sol.covariance["cam0"])["sigma_ee_frame"]
        full_sig = uncertainty_report(full.ee_T_cam["cam0"], full.covariance["cam0"])["sigma_ee_frame"]
        ratios[mode] = in_sigmas(sol.ee_T_cam["cam0"], sig, full.ee_T_cam["cam0"], full_sig)["max_ratio"]
    assert ratios["never"] > 3 and ratios["auto"] < 3, ratios
