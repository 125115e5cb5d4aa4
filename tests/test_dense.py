"""Dense reconstruction (calib3r_graph.dense, docs/dense.md) on a small rendered scene: 10 views at
320x240, solved by the real solver, depth from the images alone (SGBM on the solved poses)."""

import hashlib
import json
import re
import shutil

import cv2
import numpy as np
import open3d as o3d
import pytest
import yaml

from calib3r_graph.cli import main
from calib3r_graph.dense import check
from calib3r_graph.dense.fuse import read_dense_ply
from calib3r_graph.dense.run import DenseOptions, compute_depths
from calib3r_graph.dense.views import read_result
from calib3r_graph.io.dataset import load_dataset
from calib3r_graph.report.scene import MAX_DENSE_POINTS
from calib3r_graph.simulate import scene_from_simulation


@pytest.fixture(scope="module")
def solved(simulated, tmp_path_factory):
    """(dataset, result) of ``solve --dense --dense-source stereo`` on a rendered scene."""
    ds = simulated(seed=3, frames=10, images=True, width=320, height=240)
    out = tmp_path_factory.mktemp("dense") / "res"
    assert main(["-q", "solve", str(ds), "--out", str(out), "--jackknife", "never", "--dense",
                 "--dense-source", "stereo"]) == 0
    return ds, out


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_dense_points_lie_on_the_true_surface(solved):
    ds, out = solved
    d = read_dense_ply(out / "dense.ply")
    assert len(d["points"]) > 5000
    scene = scene_from_simulation(yaml.safe_load((ds / "ground_truth.yaml").read_text())["simulation"])
    dist = scene.scene.compute_distance(o3d.core.Tensor(d["points"].astype(np.float32))).numpy() * 1e3
    # 320x240 (f = 260 px) at 0.5-0.75 m: one view's depth is good to ~1-2 mm; a few mm is the bound
    assert np.median(dist) < 2.0 and np.percentile(dist, 90) < 6.0, (np.median(dist), np.percentile(dist, 90))
    assert np.mean(np.abs(np.linalg.norm(d["normals"], axis=1) - 1) < 1e-3) > 0.99
    assert 0 < d["confidence"].max() <= 1
    assert (out / "mesh.ply").stat().st_size > 0
    cal = json.loads((out / "calibration.json").read_text())  # solve --dense puts the figures in both
    assert cal["dense"]["points"] == len(d["points"]) and cal["dense"]["source"] == "stereo"
    assert "cross-view surface disagreement" in (out / "summary.txt").read_text()


def test_report_shows_the_dense_cloud_and_keeps_the_sparse_one(solved):
    _, out = solved
    page = (out / "report.html").read_text()
    data = json.loads(re.search(r'<script type="application/json" id="report-data">(.*?)</script>', page, re.S)[1])
    n = min(len(read_dense_ply(out / "dense.ply")["points"]), MAX_DENSE_POINTS)
    assert data["dense_points"] > 0.9 * n  # (the 1-99 % box drops stray points)
    assert f"dense cloud ({data['dense_points']} points" in page and "sparse point cloud (" in page
    assert len(page.encode()) < 10e6


def test_wrong_hand_eye_raises_the_disagreement(solved):
    ds, out = solved
    dataset, result = load_dataset(ds), read_result(out)
    state = compute_depths(dataset, result, DenseOptions(source="stereo", progress=False))
    right = check.disagreement(state.depths, state.rays, state.views, state.check_pairs)
    assert right["median_mm"] < 1.5 and right["pairs"] >= 10, right
    cam = next(iter(result.ee_T_cam))
    for kind in ({"translation_mm": 5.0}, {"rotation_deg": 0.5}):
        worst = 0.0
        for axis in range(3):  # a shift along the surfaces hides; the worst ee axis is what the check sees
            X = check.perturbed(result.ee_T_cam[cam], axis, **kind)
            poses = {v: dataset.base_T_ee[dv.frame].matrix() @ X for v, dv in state.views.items()}
            worst = max(worst, check.disagreement(state.depths, state.rays, state.views, state.check_pairs,
                                                  poses)["median_mm"])
        assert worst > 1.5 * right["median_mm"], (kind, right, worst)


def test_reconstruct_leaves_calibration_json_alone_and_names_a_failed_view(solved, tmp_path, capsys, caplog):
    ds, out = solved
    ds2, res2 = tmp_path / "ds", tmp_path / "res"
    shutil.copytree(ds, ds2)
    shutil.copytree(out, res2)
    for f in ("dense.ply", "mesh.ply", "dense.json"):
        (res2 / f).unlink()
    blank = ds2 / "images" / "cam0" / "0004.png"
    cv2.imwrite(str(blank), np.full((240, 320, 3), 128, np.uint8))  # nothing to match
    before = _sha(res2 / "calibration.json")
    assert main(["reconstruct", str(res2), str(ds2), "--dense-source", "stereo"]) == 0
    assert _sha(res2 / "calibration.json") == before
    figures = json.loads((res2 / "dense.json").read_text())
    skipped = {s["view"]: s["reason"] for s in figures["views_skipped"]}
    assert "cam0/0004" in skipped and "matching failed" in skipped["cam0/0004"]
    assert "cam0/0004 skipped: matching failed" in caplog.text
    assert "skipped cam0/0004 (matching failed" in capsys.readouterr().out
    assert figures["views_used"] >= 7 and (res2 / "dense.ply").is_file()


def test_result_folder_without_a_solve_is_a_one_line_error(solved, tmp_path, capsys):
    ds, _ = solved
    empty = tmp_path / "nothing"
    empty.mkdir()
    assert main(["reconstruct", str(empty), str(ds)]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "calibration.json" in err[0] and "solve" in err[0], err
    assert list(empty.iterdir()) == []


@pytest.mark.parametrize("source, median_mm", [("depth", 1.0), ("predictions", 3.0)])
def test_sensor_depth_and_dense_predictions_are_fused_directly(solved, tmp_path, source, median_mm):
    """The simulator's depth/ (mm PNG) and its foundation-like predictions (1.5 % smooth distortion,
    corrected by the solve's per-view depth correction) are fused without stereo."""
    ds, out = solved
    res = tmp_path / "res"
    shutil.copytree(out, res)
    assert main(["-q", "reconstruct", str(res), str(ds), "--dense-source", source]) == 0
    figures = json.loads((res / "dense.json").read_text())
    assert figures["source"] == source and figures["views_used"] == 10
    scene = scene_from_simulation(yaml.safe_load((ds / "ground_truth.yaml").read_text())["simulation"])
    pts = read_dense_ply(res / "dense.ply")["points"]
    dist = scene.scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy() * 1e3
    assert np.median(dist) < median_mm, np.median(dist)
