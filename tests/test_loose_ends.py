"""Issue 17's loose ends, each as a new user meets it: Windows-made CSV files, robots that did
not move or did not rotate, images of the wrong size, one-line errors from the libraries,
compare on raw data, and start-up and output time."""

import json
import re
import subprocess
import sys

import gtsam
import numpy as np
import pytest

from calib3r_graph.cli import main
from calib3r_graph.io.dataset import load_dataset, read_robot_poses, write_robot_poses
from tests.conftest import REPO
from tests.test_bad_input import expect_error as expect_one_line_error


# --- 4. robot_poses.csv written by Windows tools -------------------------------------------------

def test_windows_csv_with_bom_crlf_and_spaces_is_accepted(sample_copy):
    path = sample_copy / "robot_poses.csv"
    want = read_robot_poses(path)
    rows = [", ".join(line.split(",")) for line in path.read_text().splitlines()]
    path.write_bytes(b"\xef\xbb\xbf" + "\r\n".join(rows).encode() + b"\r\n")
    ds = load_dataset(sample_copy)
    assert list(ds.base_T_ee) == list(want)
    for f, p in want.items():
        assert ds.base_T_ee[f].equals(p, 1e-9)


# --- 5. a robot that did not move, or did not rotate ---------------------------------------------

def test_robot_that_did_not_move(sample_copy, tmp_path, capsys):
    poses = read_robot_poses(sample_copy / "robot_poses.csv")
    first = next(iter(poses.values()))
    write_robot_poses(sample_copy / "robot_poses.csv", {f: first for f in poses})
    line = expect_one_line_error(["solve", str(sample_copy), "--out", str(tmp_path / "o")], capsys, 4,
                                 "robot_poses.csv", "did not move", "all 8 poses are the same",
                                 "about ee x 0.00, y 0.00, z 0.00 deg", "rotate the flange 30-90 degrees")
    assert "metric scale" not in line


def test_robot_that_only_translated(sample_copy, tmp_path, capsys):
    poses = read_robot_poses(sample_copy / "robot_poses.csv")
    R0 = next(iter(poses.values())).rotation()
    # pure translations, plus a 0.5 deg wobble about the ee x axis on one pose
    new = {f: gtsam.Pose3(R0, p.translation()) for f, p in poses.items()}
    f1 = list(new)[1]
    new[f1] = gtsam.Pose3(R0.compose(gtsam.Rot3.Rx(np.radians(0.5))), new[f1].translation())
    write_robot_poses(sample_copy / "robot_poses.csv", new)
    line = expect_one_line_error(["solve", str(sample_copy), "--out", str(tmp_path / "o")], capsys, 4,
                                 "did not rotate", "translations only", "at most 0.50 deg",
                                 "about ee x 0.50, y 0.00, z 0.00 deg", "at least two different axes")
    assert "metric scale" not in line


# --- 3. image and depth sizes, and one-line errors from the libraries ----------------------------

@pytest.mark.parametrize("folder", ["images", "depth"])
def test_resized_image_is_one_line_naming_the_file(sample_copy, tmp_path, capsys, folder):
    import cv2

    path = sample_copy / folder / "cam1" / "0003.png"
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), cv2.resize(img, (160, 120), interpolation=cv2.INTER_NEAREST))
    line = expect_one_line_error(["solve", str(sample_copy), "--out", str(tmp_path / "o")], capsys, 3,
                                 str(path), "160x120", "camera cam1 320x240")
    assert ("depth map" in line) == (folder == "depth")
    assert not (tmp_path / "o").exists()


def test_image_size_reads_png_and_jpeg_headers(tmp_path):
    import cv2

    from calib3r_graph.io.dataset import image_size

    img = np.random.default_rng(0).integers(0, 255, (123, 457, 3), dtype=np.uint8)
    for name, params in (("a.png", []), ("b.jpg", [cv2.IMWRITE_JPEG_QUALITY, 90]),
                         ("c.jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])):
        cv2.imwrite(str(tmp_path / name), img, params)
        assert image_size(tmp_path / name) == (457, 123)
    (tmp_path / "d.png").write_bytes(b"not an image at all")
    from calib3r_graph.errors import InputError

    with pytest.raises(InputError, match="d.png: not a readable PNG or JPEG"):
        image_size(tmp_path / "d.png")


def test_gtsam_failure_in_solve_is_one_line(sample_copy, tmp_path, capsys):
    # zero robot noise: GTSAM's marginals meet an indeterminate system (its message is 14 lines)
    line = expect_one_line_error(["solve", str(sample_copy), "--out", str(tmp_path / "o"), "--no-cloud",
                                  "--robot-sigma-mm", "0", "--robot-sigma-deg", "0"], capsys, 4,
                                 "GTSAM: indeterminate linear system near the", "zero or non-finite noise sigma")
    assert "github.com" not in line
    assert "(camera cam" in line and not re.search(r"\b[xscel]\d+\b", line)  # the view or camera, not a GTSAM key


def test_library_errors_become_one_line_with_their_cause():
    import cv2
    import pycolmap

    from calib3r_graph.errors import library_error

    def raised(f):
        try:
            f()
        except Exception as e:  # noqa: BLE001 - the real exception of the real library
            return e
        raise AssertionError("no exception")

    e = raised(lambda: cv2.cvtColor(np.zeros((4, 4, 5), np.uint8), cv2.COLOR_BGR2GRAY))
    assert len(str(e).splitlines()) > 3
    line, code = library_error(e)
    assert line == "OpenCV: Bad number of channels (Invalid number of channels in input image:)" and code == 1

    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    x0, x1 = gtsam.symbol("x", 0), gtsam.symbol("e", 1)
    graph.add(gtsam.PriorFactorPose3(x0, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1.0)))
    values.insert(x0, gtsam.Pose3())
    values.insert(x1, gtsam.Pose3())
    graph.add(gtsam.BetweenFactorPose3(x0, x1, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1.0)))

    def blind(factor, v, H=None):  # a factor that does not depend on its variable
        if H is not None:
            H[0] = np.zeros((1, 1))
        return np.zeros(1)

    graph.add(gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, 1.0), [gtsam.symbol("l", 2)], blind))
    values.insert(gtsam.symbol("l", 2), 1.0)
    e = raised(lambda: gtsam.Marginals(graph, values))
    line, code = library_error(e)
    assert "\n" not in line and code == 4
    assert line.startswith("GTSAM: indeterminate linear system near variable l2 (a camera's metric scale)")

    e = raised(lambda: pycolmap.Reconstruction("/nonexistent/sparse"))
    line, code = library_error(e)
    assert line.startswith("pycolmap: ValueError: ") and "/nonexistent/sparse" in line and code == 1

    assert library_error(raised(lambda: {}["missing"])) is None  # ours: a bug, not a library's failure


# --- 1. compare on raw data runs the best frontend, as solve does ---------------------------------

def test_compare_on_raw_data_runs_the_best_frontend(sample_copy, tmp_path, capsys):
    import shutil

    shutil.rmtree(sample_copy / "predictions")
    out = tmp_path / "cmp"
    code = main(["-q", "compare", str(sample_copy), "--out", str(out), "--methods", "jcr-predictions,calib3r-graph"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "making them with the 'rgbd' frontend (depth/ present)" in err
    assert (sample_copy / "predictions" / "rgbd" / "pairs.npz").is_file()  # cached for the next run
    result = json.loads((out / "comparison.json").read_text())
    assert result["predictions"] == "rgbd"
    for m in ("jcr-predictions", "calib3r-graph"):
        assert result["methods"][m]["status"] == "ok", result["methods"][m]
    # the rgbd frontend's metric depth: ours lands near the truth (cam0 t = [36.55 -26.66 93.19] mm)
    X = np.array(result["methods"]["calib3r-graph"]["cameras"]["cam0"]["T_ee_cam"])
    assert np.linalg.norm(X[:3, 3] - [0.03655, -0.02666, 0.09319]) < 5e-3
    # a second run uses the cache and says nothing about frontends
    code = main(["-q", "compare", str(sample_copy), "--out", str(out), "--methods", "calib3r-graph"])
    assert code == 0 and "frontend" not in capsys.readouterr().err


# --- 6. start-up and output time --------------------------------------------------------------------

HEAVY = ("open3d", "pycolmap", "matplotlib", "scipy.stats", "plotly")


def test_solve_path_imports_no_heavy_library():
    """What `solve` imports (cli, dataset, predictions, solve, results) pulls in none of the libraries
    that take seconds to import; they are imported where they are used."""
    code = ("import sys, calib3r_graph.cli, calib3r_graph.io.dataset, calib3r_graph.io.predictions, "
            "calib3r_graph.solver.solve, calib3r_graph.io.results, calib3r_graph.evaluation.evaluate, "
            "calib3r_graph.frontends\n"
            f"print(sorted(m for m in {HEAVY!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_cloud_is_written_as_binary_ply_without_open3d(tmp_path):
    import open3d as o3d

    from calib3r_graph.io.results import voxel_down_sample, write_ply

    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 0.2, (200000, 3))
    cols = rng.uniform(0, 1, (200000, 3))
    p, c = voxel_down_sample(pts, cols, 0.01)
    # one point per occupied 1 cm voxel, the mean of its points (20^3 voxels, all occupied)
    assert len(p) == 8000
    cell = np.floor((pts - pts.min(0)) / 0.01).astype(int)
    first = np.all(cell == cell[0], axis=1)
    assert np.any(np.all(np.abs(p - pts[first].mean(0)) < 1e-12, axis=1))
    assert np.any(np.all(np.abs(c - cols[first].mean(0)) < 1e-12, axis=1))
    write_ply(tmp_path / "c.ply", p, c)
    assert (tmp_path / "c.ply").read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    back = o3d.io.read_point_cloud(str(tmp_path / "c.ply"))
    np.testing.assert_allclose(np.asarray(back.points), p, atol=1e-7)
    np.testing.assert_allclose(np.asarray(back.colors), np.round(c * 255) / 255, atol=1e-9)
