"""The public real recordings in ../shared/real (present beside CI's checkout, absent in a
user's clone: then these tests skip). Importing must find each file's pose convention from
the images and calibrate sensible intrinsics."""

import json

import gtsam
import numpy as np
import pytest

from calib3r_graph.cli import main
from calib3r_graph.evaluation.compare import errors_against
from calib3r_graph.importers import import_recording
from calib3r_graph.io.dataset import ee_T_cam_by_camera, load_dataset
from calib3r_graph.solver.uncertainty import systematic_error_gain
from tests.conftest import SHARED

REAL = SHARED / "real"
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason="../shared/real (public recordings) is not beside this checkout")


@needs_real
@pytest.mark.slow
def test_rwhe_kuka_import(tmp_path):
    report = import_recording("rwhe", REAL / "rwhe_kuka_1", tmp_path / "rwhe", (28, 17), progress=False)
    assert "* as given (base_T_ee), m " in report
    ds = load_dataset(tmp_path / "rwhe")
    assert len(ds.frames) == 30
    cam = ds.cameras["cam0"]
    assert (cam.width, cam.height) == (1928, 1208)
    assert 1900 < cam.params[0] < 2200 and abs(cam.params[2] - 964) < 40
    # twelve poses are pure translations with the orientation of pose 1
    R0 = ds.base_T_ee[ds.frames[0]].rotation().matrix()
    same = sum(np.allclose(ds.base_T_ee[f].rotation().matrix(), R0, atol=1e-4) for f in ds.frames)
    assert same >= 12


@needs_real
@pytest.mark.slow
def test_tabb_import_detects_inverted_millimetres(tmp_path):
    report = import_recording("tabb", REAL / "tabb_ds1", tmp_path / "tabb", progress=False)
    assert "* inverted (file holds ee_T_base), mm" in report
    ds = load_dataset(tmp_path / "tabb")
    assert len(ds.frames) == 88 and ds.pattern["inner_corners"] == [8, 6]
    assert abs(ds.pattern["square_size"] - 0.0285) < 1e-9
    reach = max(np.linalg.norm(p.translation()) for p in ds.base_T_ee.values())
    assert 0.3 < reach < 1.5  # metres, a Denso VS-6577's workspace
    # The board alone says fx 1059; the robot's metric motion moves it to about 1100.
    assert 1090 < ds.cameras["cam0"].params[0] < 1110
    # The flange hardly turns about axes that would fix ee y: systematic errors gain 8x there.
    gain, axis = systematic_error_gain(ds.base_T_ee, ds.frames)
    assert 7 < gain < 10 and abs(axis[1]) > 0.99


def import_and_compare(tmp_path, fmt, src, board, methods, with_result=False):
    """import -> colmap frontend (RGB only) -> compare; {method: (e_t m, e_theta rad)} to pattern-ba
    (and, ``with_result``, comparison.json's result and the reference {camera: Pose3} too)."""
    root = tmp_path / fmt
    import_recording(fmt, REAL / src, root, board, progress=False)
    assert main(["-q", "predict", str(root), "--frontend", "colmap"]) == 0
    out = tmp_path / "cmp"
    assert main(["-q", "compare", str(root), "--out", str(out), "--predictions", "colmap", "--methods", methods]) == 0
    res = json.loads((out / "comparison.json").read_text())
    assert all(r["status"] == "ok" for r in res["methods"].values())
    ref = ee_T_cam_by_camera(res["methods"]["pattern-ba"]["cameras"])
    errs = {m: e["cam0"] for m, e in errors_against(res, ref).items()}
    return (errs, res, ref) if with_result else errs


@needs_real
@pytest.mark.slow
def test_rwhe_patternless_agrees_with_the_pattern_reference(tmp_path):
    """The issue's acceptance on rwhe_kuka_1, end to end: import, the colmap frontend (RGB only),
    compare. Ours never uses the board's geometry, yet lands within its own 3 total sigma of
    pattern-ba on every ee axis, within 3 mm / 0.05 deg (the reference repeats to about 1 mm between
    the recording's halves, so it judges tolerances from 3 mm: docs/real-recordings.md), and beats
    both two-stage pipelines in translation and rotation. (It was 0.76-1.03 mm from it in three
    runs: COLMAP's reconstruction differs from run to run, its RANSAC and mapper seeds fixed and on
    one thread too, so a 1 mm bound failed one run in three.)"""
    from calib3r_graph.io.results import tangent_in_ee_frame

    errs, res, ref = import_and_compare(tmp_path, "rwhe", "rwhe_kuka_1", (28, 17),
                                        "park,pattern-ba,jcr-colmap,jcr-predictions,calib3r-graph", with_result=True)
    ours = errs["calib3r-graph"]
    assert ours[0] < 3e-3 and np.degrees(ours[1]) < 0.05, ours
    cam = res["methods"]["calib3r-graph"]["cameras"]["cam0"]
    X = ee_T_cam_by_camera(res["methods"]["calib3r-graph"]["cameras"])["cam0"]
    d = tangent_in_ee_frame(X.rotation().matrix(), gtsam.Pose3.Logmap(ref["cam0"].between(X)))
    z = {k: abs(d[k]) / cam["sigma_ee_frame"][k] for k in d}
    assert max(z.values()) < 3, z
    for two_stage in ("jcr-colmap", "jcr-predictions"):
        assert ours[0] < errs[two_stage][0] and ours[1] < errs[two_stage][1], (two_stage, errs[two_stage])


@needs_real
@pytest.mark.slow
def test_tabb_patternless_rotation_agrees_with_the_pattern_reference(tmp_path):
    """tabb_ds1, end to end: the rotation meets the 0.3 deg acceptance. The translation is
    2.1 cm from pattern-ba, which this recording cannot decide (docs/real-recordings.md: both
    methods move 5-25 mm between halves of the data and noise models); the bound only guards
    that figure."""
    errs = import_and_compare(tmp_path, "tabb", "tabb_ds1", None, "park,pattern-ba,calib3r-graph")
    ours = errs["calib3r-graph"]
    assert np.degrees(ours[1]) < 0.3 and ours[0] < 0.03, ours
    assert ours[1] < errs["park"][1]


@needs_real
@pytest.mark.slow
def test_rwhe_kuka_2_reference_holds_and_ours_is_within_its_sigmas(tmp_path):
    """rwhe_kuka_2, end to end (import, colmap frontend, compare --halves). The camera orbits the
    board, so the robot measures the board's scale only to percent (0.966 +- 0.008 from the
    noise model, +- 1.6 % more from the kinematic error field): pattern-ba keeps the nominal
    size within its print tolerance, agrees with OpenCV's solvers and repeats between the halves
    3x better than 5 mm. Ours takes its metric scale from the same robot and lands 15 mm away
    along the optical axis, which its total sigma (model + kinematic error field) covers within
    3 sigma on every ee axis; so do its halves."""
    root, out = tmp_path / "k2", tmp_path / "cmp"
    import_recording("rwhe", REAL / "rwhe_kuka_2", root, (24, 17), progress=False)
    assert main(["-q", "predict", str(root), "--frontend", "colmap"]) == 0
    assert main(["-q", "compare", str(root), "--out", str(out), "--predictions", "colmap", "--methods",
                 "tsai,park,pattern-ba,calib3r-graph", "--halves", "--no-report"]) == 0
    res = json.loads((out / "comparison.json").read_text())
    assert all(r["status"] == "ok" for r in res["methods"].values())
    ref = ee_T_cam_by_camera(res["methods"]["pattern-ba"]["cameras"])
    errs = {m: e["cam0"] for m, e in errors_against(res, ref).items()}
    for opencv in ("tsai", "park"):
        assert errs[opencv][0] < 1e-3 and np.degrees(errs[opencv][1]) < 0.1, (opencv, errs[opencv])
    check = res["reference_validation"]
    assert check["validated"] and check["halves_mm"] < 5 / 3, check
    assert res["in_sigmas"]["calib3r-graph"]["cam0"]["max_ratio"] <= 3.0, res["in_sigmas"]
    halves = json.loads((out / "halves.json").read_text())
    assert halves["in_sigmas"]["calib3r-graph"]["cam0"]["max_ratio"] <= 3.0, halves["in_sigmas"]
    # The noise model alone would not cover it (this is what the systematic part is for).
    X = ee_T_cam_by_camera(res["methods"]["calib3r-graph"]["cameras"])["cam0"]
    assert np.linalg.norm(X.translation() - ref["cam0"].translation()) > 8e-3
