"""Importers: the simulator's rendered recording written in each public format (including the
variants: bmp, im_XX names, misspelt square-size file, inverted poses in mm), then imported."""

import shutil

import cv2
import numpy as np
import pytest

from calib3r_graph.cli import main
from calib3r_graph.errors import InputError
from calib3r_graph.importers import import_recording
from calib3r_graph.io.dataset import load_dataset, load_ground_truth, pose_from_dict


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    from calib3r_graph.simulate import SimOptions, simulate

    return simulate(tmp_path_factory.mktemp("r") / "d", SimOptions(seed=51, frames=8, images=True, pattern=True),
                    progress=False)


def true_poses(root):
    gt = load_ground_truth(root)
    return {f: pose_from_dict(d) for f, d in gt["base_T_ee_true"].items()}


def write_rwhe(root, dst, bmp=False, misspelt=False):
    dst.mkdir()
    lines = []
    for i, (f, E) in enumerate(sorted(true_poses(root).items()), 1):
        img = cv2.imread(str(root / "images" / "cam0" / f"{f}.png"))
        cv2.imwrite(str(dst / (f"im_{i:02d}.bmp" if bmp else f"{i:02d}.png")), img)
        lines.append("\t".join(f"{x:.9f}" for x in E.matrix().ravel()))
    (dst / "RobotPosesVec.txt").write_text("\n".join(lines) + "\n")
    (dst / ("sqauresize.txt" if misspelt else "squaresize.txt")).write_text("30mm")


def write_tabb(root, dst):
    dst.mkdir()
    poses = sorted(true_poses(root).items())
    blocks = [str(len(poses))]
    for i, (f, E) in enumerate(poses):
        shutil.copyfile(root / "images" / "cam0" / f"{f}.png", dst / f"image{i:02d}.png")
        M = E.inverse().matrix()  # this format's file holds ee_T_base, in mm
        M[:3, 3] *= 1000
        blocks.append("\n".join(" ".join(f"{x:.6f}" for x in row) for row in M))
    (dst / "robot_cali.txt").write_text("\n\n".join(blocks) + "\n")
    (dst / "calibration_object.txt").write_text("tile size: 30 mm\n9x6 chessboard\n")


def assert_imported(dst, root):
    ds = load_dataset(dst)
    truth = true_poses(root)
    assert len(ds.frames) == 8 and ds.pattern["inner_corners"] == [9, 6]
    for (f, E), (g, T) in zip(sorted(ds.base_T_ee.items()), sorted(truth.items())):
        np.testing.assert_allclose(E.matrix(), T.matrix(), atol=1e-5)
    cam = ds.cameras["cam0"]
    assert cam.model == "OPENCV"
    true_K = load_dataset(root).cameras["cam0"].K
    # Calibrated from 8 views of a small board lying on the table: focal within 1.5 %,
    # principal point within 10 px is what such a calibration delivers.
    np.testing.assert_allclose(np.diag(cam.K)[:2], np.diag(true_K)[:2], rtol=0.015)
    np.testing.assert_allclose(cam.K[:2, 2], true_K[:2, 2], atol=10.0)


@pytest.mark.slow
@pytest.mark.parametrize("bmp,misspelt", [(False, False), (True, True)])
def test_rwhe_variants(rendered, tmp_path, capsys, bmp, misspelt):
    src = tmp_path / "raw"
    write_rwhe(rendered, src, bmp, misspelt)
    assert main(["import", "rwhe", str(src), str(tmp_path / "ds"), "--board", "9x6"]) == 0
    out = capsys.readouterr().out
    assert "* as given (base_T_ee), m " in out
    assert_imported(tmp_path / "ds", rendered)


@pytest.mark.slow
def test_tabb_inverted_millimetres_are_detected(rendered, tmp_path, capsys):
    src = tmp_path / "raw"
    write_tabb(rendered, src)
    assert main(["import", "tabb", str(src), str(tmp_path / "ds")]) == 0
    assert "* inverted (file holds ee_T_base), mm" in capsys.readouterr().out
    assert_imported(tmp_path / "ds", rendered)


def test_bad_recordings(tmp_path, capsys):
    src = tmp_path / "raw"
    src.mkdir()
    assert main(["import", "rwhe", str(src), str(tmp_path / "o"), "--board", "9x6"]) == 3
    assert "RobotPosesVec.txt: missing" in capsys.readouterr().err
    (src / "RobotPosesVec.txt").write_text("1 2 3\n")
    with pytest.raises(InputError, match="16 numbers"):
        import_recording("rwhe", src, tmp_path / "o", (9, 6))
    assert main(["import", "rwhe", str(src), str(tmp_path / "o"), "--board", "9by6"]) == 3
