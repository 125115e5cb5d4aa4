"""Dense reconstruction (calib3r_graph.dense, docs/dense.md) on a small rendered scene: 10 views at
320x240, solved by the real solver, depth from the images alone (SGBM on the solved poses), from the
simulator's sensor depth and from its predictions; the report that ``reconstruct`` rewrites; bad input
(a blank image, a wrong pose, a folder without a solve, a run that fails) never touching the folder."""

import csv
import hashlib
import io
import json
import re
import shutil
import sys

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
from calib3r_graph.report import solve_page
from calib3r_graph.report.scene import MAX_DENSE_POINTS, dense_cloud_arrays, palette_colours
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


def _folder_hashes(folder):
    return {p.name: _sha(p) for p in sorted(folder.iterdir())}


def _report_data(page: str) -> dict:
    return json.loads(re.search(r'<script type="application/json" id="report-data">(.*?)</script>', page, re.S)[1])


def _truth_distance_mm(ds, points):
    scene = scene_from_simulation(yaml.safe_load((ds / "ground_truth.yaml").read_text())["simulation"])
    return scene.scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy() * 1e3


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
    assert main(["reconstruct", str(res2), str(ds2), "--dense-source", "stereo", "--no-report"]) == 0
    assert _sha(res2 / "calibration.json") == before
    figures = json.loads((res2 / "dense.json").read_text())
    skipped = {s["view"]: s["reason"] for s in figures["views_skipped"]}
    assert "cam0/0004" in skipped and "matching failed" in skipped["cam0/0004"]
    assert "cam0/0004 skipped: matching failed" in caplog.text
    assert "skipped cam0/0004 (matching failed" in capsys.readouterr().out
    assert figures["views_used"] >= 7 and (res2 / "dense.ply").is_file()


@pytest.mark.parametrize("shift_mm", [5.0, 100.0])
def test_a_view_whose_pose_disagrees_with_its_image_is_named_and_skipped(solved, tmp_path, caplog, shift_mm):
    """trajectory.csv's pose of view 0007 moved along base x: 5 mm still matches, and its depth lands
    ~6 mm off the other views' surfaces (the consistency step skips it); 100 mm makes the matching fail."""
    ds, out = solved
    res = tmp_path / "res"
    shutil.copytree(out, res)
    path = res / "trajectory.csv"
    rows = list(csv.reader(path.read_text().splitlines()))
    for r in rows[1:]:
        if r[1] == "0007":
            r[2] = repr(float(r[2]) + shift_mm * 1e-3)
    path.write_text("".join(",".join(r) + "\n" for r in rows))
    assert main(["-q", "reconstruct", str(res), str(ds), "--dense-source", "stereo", "--no-report"]) == 0
    figures = json.loads((res / "dense.json").read_text())
    skipped = {s["view"]: s["reason"] for s in figures["views_skipped"]}
    why = "disagrees with the image" if shift_mm < 50 else "matching failed"
    assert why in skipped.get("cam0/0007", ""), skipped
    assert "cam0/0007 skipped: " in caplog.text and why in caplog.text
    assert figures["views_used"] >= 7
    # what was fused is the other views' surface, not the misplaced view's
    dist = _truth_distance_mm(ds, read_dense_ply(res / "dense.ply")["points"])
    assert np.median(dist) < 2.0 and np.percentile(dist, 90) < 6.0, (np.median(dist), np.percentile(dist, 90))


@pytest.mark.parametrize("case, named", [("empty", "calibration.json: missing"),
                                         ("no trajectory", "trajectory.csv: missing"),
                                         ("corrupt calibration", "calibration.json: not a calibration.json"),
                                         ("no folder", "no such result folder")])
def test_result_folder_without_a_solve_is_a_one_line_error(solved, tmp_path, capsys, case, named):
    ds, out = solved
    res = tmp_path / "res"
    if case != "no folder":
        res.mkdir()
    if case == "no trajectory":
        shutil.copy(out / "calibration.json", res)
    if case == "corrupt calibration":
        shutil.copy(out / "trajectory.csv", res)
        (res / "calibration.json").write_text('{"cameras": ')
    before = _folder_hashes(res) if res.exists() else None
    assert main(["reconstruct", str(res), str(ds)]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and named in err[0] and "Traceback" not in err[0], err
    if case != "no folder":
        assert "solve" in err[0]
        assert _folder_hashes(res) == before  # nothing written, nothing touched
    else:
        assert not res.exists()


def test_a_failed_reconstruct_leaves_the_result_folder_as_it_was(solved, tmp_path, capsys):
    """No view has a readable image: a one-line error, and every file of the result folder (the
    calibration.json, the dense.ply, report.html and summary.txt of the earlier run) is unchanged."""
    ds, out = solved
    ds2, res = tmp_path / "ds", tmp_path / "res"
    shutil.copytree(ds, ds2, ignore=shutil.ignore_patterns("images", "depth"))
    shutil.copytree(out, res)
    before = _folder_hashes(res)
    assert main(["reconstruct", str(res), str(ds2), "--dense-source", "stereo"]) == 4
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no view gave a depth map" in err[0] and "no image" in err[0], err
    assert _folder_hashes(res) == before


def test_dense_predictions_are_fused_directly(solved, tmp_path):
    """The simulator's foundation-like predictions (1.5 % smooth distortion, corrected by the solve's
    per-view depth correction) are fused without stereo."""
    ds, out = solved
    res = tmp_path / "res"
    shutil.copytree(out, res)
    assert main(["-q", "reconstruct", str(res), str(ds), "--dense-source", "predictions", "--no-report"]) == 0
    figures = json.loads((res / "dense.json").read_text())
    assert figures["source"] == "predictions" and figures["views_used"] == 10
    dist = _truth_distance_mm(ds, read_dense_ply(res / "dense.ply")["points"])
    assert np.median(dist) < 3.0, np.median(dist)


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_reconstruct_on_an_rgbd_dataset_fuses_its_depth_shows_progress_and_rewrites_the_report(
        solved, tmp_path, monkeypatch):
    """The plain command on a dataset with depth/ (the simulator's RGB-D: mm PNGs) fuses the sensor
    depth (no --dense-source), draws its progress bars on a terminal, and replaces report.html with one
    rebuilt from the folder's files: the new dense cloud, the sparse cloud in the legend, the same robot
    residuals and view pairs as the solve's page; calibration.json stays byte for byte."""
    ds, out = solved
    res = tmp_path / "res"
    shutil.copytree(out, res)
    before, old = _sha(res / "calibration.json"), _report_data((res / "report.html").read_text())
    terminal = _Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    assert main(["reconstruct", str(res), str(ds)]) == 0
    assert "dense depth" in terminal.getvalue() and "TSDF fusion" in terminal.getvalue()
    figures = json.loads((res / "dense.json").read_text())
    assert figures["source"] == "depth" and figures["views_used"] == 10
    dist = _truth_distance_mm(ds, read_dense_ply(res / "dense.ply")["points"])
    # the sensor depth is true in its own frame, the views sit at their solved poses: 0.3-0.8 mm off the
    # truth along the optical axes in this 10-view solve, plus the mm PNG's rounding (0.29 mm RMS) and
    # the 2 mm voxel's surface extraction (measured: median 0.89 mm, p90 1.24 mm)
    assert np.median(dist) < 1.5 and np.percentile(dist, 90) < 3.5, (np.median(dist), np.percentile(dist, 90))
    assert _sha(res / "calibration.json") == before

    page = (res / "report.html").read_text()
    data = _report_data(page)
    assert data["dense_points"] == len(dense_cloud_arrays(res)[0]) != old["dense_points"]
    assert "Dense cloud (depth, 10 views)" in page and "sparse point cloud (" in page
    assert len(page.encode()) < 10e6
    assert data["pairs"] == old["pairs"] and len(data["pairs"]) >= 10
    for new_row, old_row in zip(data["robot_poses"], old["robot_poses"], strict=True):
        assert new_row["view"] == old_row["view"] and new_row["flagged"] == old_row["flagged"]
        assert abs(new_row["chi2"] - old_row["chi2"]) < 1e-6 * max(1.0, old_row["chi2"])


def test_the_report_keeps_under_its_size_limit_and_says_what_it_lacks(solved, tmp_path, monkeypatch):
    ds, out = solved
    dataset = load_dataset(ds)
    monkeypatch.setattr(solve_page, "MAX_PAGE_BYTES", 6_500_000)  # room for ~60 k of the dense points
    page = solve_page.result_report_html(out, dataset)
    assert len(page.encode()) <= 6_500_000 and 1000 < _report_data(page)["dense_points"] < 100000
    res = tmp_path / "res"  # solved with --no-report: no view pairs to carry over
    shutil.copytree(out, res, ignore=shutil.ignore_patterns("report.html", "*.ply"))
    page = solve_page.result_report_html(res, dataset)
    assert "did not hold them" in page and _report_data(page)["pairs"] is None
    assert _report_data(page)["cloud_points"] > 1000  # the sparse cloud from the predictions and views.npz


def test_palette_colours_are_within_half_a_level():
    rgb = np.random.default_rng(0).random((5000, 3))
    index, palette = palette_colours(rgb)
    back = np.array([[int(palette[i][k:k + 2], 16) for k in (1, 3, 5)] for i in index]) / 255
    assert np.abs(back - rgb).max() <= 0.5 / 15 + 1e-9 and len(palette) <= 16 ** 3
