"""The paper's metric reconstruction accuracy (Calib3R, Table II) in ``evaluate`` and ``compare``: the
board's corners detected in the images, taken in 3D from the reconstruction (corrected depth, or
triangulated from the solved views), m_s − s, σ_s and δ_s; and, with the simulator's geometry, the
reconstruction's point-to-surface distances."""

import json
import shutil

import numpy as np
import pytest

from calib3r_graph.cli import main
from calib3r_graph.evaluation.evaluate import metric_scale_accuracy
from calib3r_graph.evaluation.pattern import detect
from calib3r_graph.io.dataset import load_dataset
from calib3r_graph.io.predictions import load_predictions
from calib3r_graph.io.results import read_views
from tests.conftest import SAMPLE


@pytest.fixture(scope="module")
def solved_sample(tmp_path_factory):
    out = tmp_path_factory.mktemp("solved") / "sample"
    assert main(["-q", "solve", str(SAMPLE), "--out", str(out), "--no-report"]) == 0
    return out


@pytest.fixture(scope="module")
def sample_state(solved_sample):
    ds = load_dataset(SAMPLE)
    preds = load_predictions(ds.root, "sim", ds.cameras, set(ds.frames))
    return ds, preds, read_views(solved_sample / "views.npz"), {c: detect(ds, c) for c in ds.cameras}


def test_evaluate_writes_the_papers_metric_scale(solved_sample, capsys):
    assert main(["evaluate", str(solved_sample), str(SAMPLE)]) == 0
    out = capsys.readouterr().out
    assert "metric scale on the board (16 views, depth): m_s - s = " in out
    report = json.loads((solved_sample / "evaluation.json").read_text())
    m = report["metric_scale"]
    assert set(m) >= {"m_s_mm", "m_s_minus_s_mm", "sigma_s_mm", "delta_s_percent", "detections"}
    assert m["detections"] == 16 and m["source"] == "depth" and m["square_size_mm"] == pytest.approx(30.0)
    assert m["m_s_minus_s_mm"] == pytest.approx(m["m_s_mm"] - 30.0)
    assert m["delta_s_percent"] == pytest.approx(abs(m["m_s_minus_s_mm"]) / 30.0 * 100)
    # the sample's predictions have 1.5 % smooth depth distortion; the solved correction removes it
    assert abs(m["m_s_minus_s_mm"]) < 0.15 and m["delta_s_percent"] < 0.5
    assert 0.1 < m["sigma_s_mm"] < 1.5
    # the simulator's geometry is known: the reconstruction lies on the true surface
    r = report["reconstruction"]
    assert r["median_mm"] < 1.5 and r["median_mm"] < r["p90_mm"] < 4.0 and r["points"] > 50000
    assert report["hand_eye"]["cam0"]["e_t_m"] < 2e-3


def test_metric_scale_follows_the_reconstructions_scale(sample_state):
    """Measured from the solved depth: 1 % more depth scale is 1 % larger squares."""
    ds, preds, states, dets = sample_state
    base = metric_scale_accuracy(ds, preds, states, dets)
    states.depth_scale = {v: s * 1.01 for v, s in states.depth_scale.items()}
    try:
        scaled = metric_scale_accuracy(ds, preds, states, dets)
    finally:
        states.depth_scale = {v: s / 1.01 for v, s in states.depth_scale.items()}
    assert scaled["m_s_mm"] == pytest.approx(base["m_s_mm"] * 1.01, rel=1e-6)
    # without the solved depth correction, the predictions' distortion shows up as scale error or spread
    corrections = states.depth_correction
    states.depth_correction = {v: np.zeros_like(c) for v, c in corrections.items()}
    try:
        raw = metric_scale_accuracy(ds, preds, states, dets)
    finally:
        states.depth_correction = corrections
    assert raw["sigma_s_mm"] > base["sigma_s_mm"] or abs(raw["m_s_minus_s_mm"]) > abs(base["m_s_minus_s_mm"])


def test_triangulated_from_the_solved_views_where_depth_is_sparse(sample_state):
    ds, preds, states, dets = sample_state
    m = metric_scale_accuracy(ds, preds, states, dets, use_depth=False)
    assert m["source"] == "triangulation" and m["detections"] == 16
    assert m["distances"] == 8 * 6 + 9 * 5  # one board: every adjacent pair of the 9x6 corners once
    assert abs(m["m_s_minus_s_mm"]) < 0.1 and m["sigma_s_mm"] < 0.3
    # sparse depth (as the colmap frontend makes): the views fall back to triangulation by themselves
    dense = {v: vp.conf for v, vp in preds.views.items()}
    for vp in preds.views.values():
        keep = np.zeros(vp.conf.shape, bool)
        keep[::7, ::7] = True
        vp.conf = np.where(keep, vp.conf, 0)
    try:
        auto = metric_scale_accuracy(ds, preds, states, dets)
    finally:
        for v, conf in dense.items():
            preds.views[v].conf = conf
    assert auto["source"] == "triangulation" and auto["m_s_mm"] == pytest.approx(m["m_s_mm"])


def test_evaluate_without_ground_truth_still_measures_the_board(solved_sample, tmp_path):
    root = tmp_path / "sample"
    shutil.copytree(SAMPLE, root)
    (root / "ground_truth.yaml").unlink()
    assert main(["-q", "evaluate", str(solved_sample), str(root)]) == 0
    report = json.loads((solved_sample / "evaluation.json").read_text())
    assert "hand_eye" not in report and "reconstruction" not in report
    assert report["metric_scale"]["delta_s_percent"] < 0.5


def test_compare_gives_delta_s_for_ours(tmp_path, capsys):
    out = tmp_path / "cmp"
    assert main(["-q", "compare", str(SAMPLE), "--out", str(out), "--methods", "park,calib3r-graph"]) == 0
    result = json.loads((out / "comparison.json").read_text())
    m = result["methods"]["calib3r-graph"]["metric_scale"]
    assert m["detections"] == 16 and m["delta_s_percent"] < 0.5
    assert "metric_scale" not in result["methods"]["park"]  # no reconstruction
    md = (out / "comparison.md").read_text()
    assert "δ_s (%)" in md and "| calib3r-graph | " in md.split("Metric reconstruction accuracy")[1]


def test_evaluate_a_result_without_views_npz_still_gives_the_hand_eye_errors(solved_sample, tmp_path, capsys):
    old = tmp_path / "old"
    shutil.copytree(solved_sample, old)
    (old / "views.npz").unlink()  # as solved before views.npz existed
    assert main(["evaluate", str(old), str(SAMPLE)]) == 0
    assert "not evaluated: metric scale and reconstruction: " in capsys.readouterr().out
    report = json.loads((old / "evaluation.json").read_text())
    assert report["hand_eye"]["cam0"]["e_t_m"] < 2e-3 and "metric_scale" not in report
