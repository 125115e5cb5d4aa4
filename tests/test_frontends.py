"""Frontends on the rendered simulator images: RGB-D (sensor depth + SIFT) and colmap
(RGB only), against the goals for 12 poses; and solve's automatic frontend choice."""

import shutil

import numpy as np
import pytest

from calib3r_graph.cli import main
from calib3r_graph.evaluation.evaluate import hand_eye_errors
from calib3r_graph.frontends import run_frontend
from calib3r_graph.io.dataset import load_dataset, load_ground_truth
from calib3r_graph.io.predictions import load_predictions
from calib3r_graph.solver.solve import SolveOptions, solve


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    from calib3r_graph.simulate import SimOptions, simulate

    return simulate(tmp_path_factory.mktemp("rendered") / "d", SimOptions(seed=31, frames=12, images=True),
                    progress=False)


def solve_with(root, name, **kw):
    ds = load_dataset(root)
    preds = load_predictions(root, name, ds.cameras, set(ds.frames))
    sol = solve(ds, preds, SolveOptions(**kw))
    return preds, sol, hand_eye_errors(sol.ee_T_cam, load_ground_truth(root))["cam0"]


@pytest.mark.slow
def test_rgbd_frontend_12_poses(rendered):
    run_frontend(load_dataset(rendered), "rgbd", progress=False)
    preds, sol, e = solve_with(rendered, "rgbd")
    assert preds.info["metric_depth"] is True
    assert len(preds.pairs) >= 12 and min(len(p.uv_a) for p in preds.pairs) >= 30
    assert e["e_t_m"] <= 3e-3 and np.degrees(e["e_theta_rad"]) <= 0.2, e
    # sensor depth is metric: the metric scale must come out as 1
    assert sol.metric_scale["cam0"][0] == pytest.approx(1.0, abs=0.01)


@pytest.mark.slow
def test_colmap_frontend_12_poses_rgb_only(rendered, tmp_path):
    rgb_only = tmp_path / "rgb"
    shutil.copytree(rendered, rgb_only, ignore=shutil.ignore_patterns("depth", "predictions"))
    run_frontend(load_dataset(rgb_only), "colmap", progress=False)
    preds, sol, e = solve_with(rgb_only, "colmap")
    assert preds.info["registered"] == 12
    assert e["e_t_m"] <= 5e-3 and np.degrees(e["e_theta_rad"]) <= 0.3, e
    _, _, e2 = solve_with(rgb_only, "colmap", init="colmap")
    assert e2["e_t_m"] <= 5e-3 and np.degrees(e2["e_theta_rad"]) <= 0.3, e2


@pytest.mark.slow
def test_solve_without_predictions_runs_the_best_frontend(rendered, tmp_path, capsys):
    d = tmp_path / "d"
    shutil.copytree(rendered, d, ignore=shutil.ignore_patterns("predictions"))
    assert main(["solve", str(d), "--out", str(tmp_path / "o"), "--no-cloud"]) == 0
    assert "'rgbd' frontend" in capsys.readouterr().err
    assert (d / "predictions" / "rgbd" / "pairs.npz").is_file()  # cached for the next run
