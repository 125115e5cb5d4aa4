"""Imports that cannot be trusted are refused, with one line that names the file and the likely
cause: no pose convention fits the board's motion (images and poses mispaired), or a board that
looks the same turned by 180° whose turn the robot's motion cannot tell. The chosen unit and
direction are always printed, a departure from the declared or default one is warned about, and
--unit / --direction force them (still checked).

Rendered views of a checkerboard (tests/test_boards.py's renderer) for the command line; board
corners projected with known noise for the function-level checks."""

import cv2
import gtsam
import numpy as np
import pytest

from calib3r_graph.cli import main
from calib3r_graph.errors import InputError
from calib3r_graph.evaluation import pattern
from calib3r_graph.importers import FIT_RATIO, apply_convention, choose_convention, convention_lines
from calib3r_graph.io import board_turns, boards
from calib3r_graph.io.dataset import load_dataset
from tests.test_boards import K, look_at, render_view

EE_T_CAM = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.02, -0.03, np.pi / 2), np.array([0.04, -0.03, 0.09]))
BASE_T_BOARD = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.array([0.5, 0.1, 0.0]))


def rig(board, n, seed, tilt_deg=25.0, cam_T_boards=None):
    """``(base_T_ee, cam_T_board)`` lists of a camera on a robot looking at ``board`` on the table."""
    rng = np.random.default_rng(seed)
    centre = boards.points(board)[:, :2].mean(0)
    views = cam_T_boards or [look_at(rng, rng.uniform(0.35, 0.45), target=centre + rng.uniform(-0.02, 0.02, 2),
                                     tilt_deg=tilt_deg) for _ in range(n)]
    return [BASE_T_BOARD.compose(P.inverse()).compose(EE_T_CAM.inverse()) for P in views], views


@pytest.fixture(scope="module")
def rendered():
    """Eight rendered views of a 9x6 checkerboard and the robot's base_T_ee for each."""
    board = boards.parse_board("9x6:0.03")
    rng = np.random.default_rng(4)
    poses, views = rig(board, 8, 4)
    return [render_view(board, P, rng=rng) for P in views], poses


def write(folder, images, poses, names, unit="m"):
    """Images under ``names`` and a pose file of row-major 4x4s, one per line, in capture order."""
    (folder / "img").mkdir(parents=True)
    for img, name in zip(images, names):
        cv2.imwrite(str(folder / "img" / f"{name}.png"), img)
    lines = []
    for E in poses:
        M = E.matrix()
        M[:3, 3] *= 1000 if unit == "mm" else 1
        lines.append(" ".join(f"{x:.9f}" for x in M.ravel()))
    (folder / "poses.txt").write_text("\n".join(lines) + "\n")
    return ["--images", str(folder / "img"), "--poses", str(folder / "poses.txt"), "--pose-format", "matrix",
            "--board", "9x6:0.03"]


def test_mispaired_images_and_poses_are_refused(rendered, tmp_path, capsys):
    """Images named so that their sorted order is not the capture order (the poses' order): no
    convention fits, exit 3, one line naming the pose file and the pairing used, nothing written."""
    images, poses = rendered
    names = ["delta", "alpha", "hotel", "bravo", "golf", "charlie", "foxtrot", "echo"]  # capture order
    args = write(tmp_path / "raw", images, poses, names)
    dst = tmp_path / "ds"
    assert main(["import", "files", str(dst), *args]) == 3
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    assert "poses.txt" in err and "no pose convention fits" in err
    causes = [err.index(c) for c in ("mispaired (they were paired in sorted order", "flipped between images",
                                     "a wrong pose format")]
    assert causes == sorted(causes)
    assert not dst.exists()


def test_unit_and_direction_are_printed_warned_and_forced(rendered, tmp_path, capsys):
    images, poses = rendered
    args = write(tmp_path / "raw", images, poses, [f"shot_{i}" for i in range(8)], unit="mm")
    # The images say mm where the default is m: chosen, printed, and warned about.
    assert main(["import", "files", str(tmp_path / "a"), *args]) == 0
    out = capsys.readouterr().out
    assert "using 'as given (base_T_ee), mm' (chosen" in out
    assert "! the poses fit the images as 'as given (base_T_ee), mm', not as base_T_ee in m (the default unit" in out
    E = load_dataset(tmp_path / "a").base_T_ee
    np.testing.assert_allclose(E["0000"].matrix(), poses[0].matrix(), atol=1e-6)
    # Forced to what does not fit: refused (forcing skips the choice, not the check), nothing written.
    assert main(["import", "files", str(tmp_path / "c"), *args, "--unit", "m", "--direction", "base_T_ee"]) == 3
    err = capsys.readouterr().err
    assert "with direction base_T_ee and unit m (forced)" in err and "'as given (base_T_ee), mm'" in err
    assert not (tmp_path / "c").exists()


def projected(board, views, sigma_px, seed=0):
    """Detections ``{frame: (uv, None)}`` of the board's corners projected with ``sigma_px`` noise,
    and their PnP poses."""
    rng = np.random.default_rng(seed)
    obj = boards.points(board)
    dets, poses = {}, {}
    for i, P in enumerate(views):
        M = P.matrix()
        uv = cv2.projectPoints(obj, cv2.Rodrigues(M[:3, :3])[0], M[:3, 3], K, np.zeros(4))[0].reshape(-1, 2)
        uv = uv + rng.normal(scale=sigma_px, size=uv.shape)
        ok, r, t = cv2.solvePnP(obj, uv, K, np.zeros(4))
        dets[f"{i:04d}"] = (uv, None)
        poses[f"{i:04d}"] = gtsam.Pose3(gtsam.Rot3(cv2.Rodrigues(r)[0]), t.ravel())
    return dets, poses


def check(board, base_T_ee, views, sigma_px, order=None):
    dets, P = projected(board, views, sigma_px)
    mats = {f"{i:04d}": base_T_ee[j].matrix() for i, j in enumerate(order or range(len(views)))}
    return choose_convention(mats, P, board_turns.pose_covariances(board, dets, P, K, np.zeros(4)), board)


def test_refusal_follows_from_the_detections():
    """What a correct convention leaves is predicted from the detections' own PnP noise, so the same
    correct recording passes with precise corners and with 2 px corners (whose residual is ~20x
    larger), and a pairing one off is refused in both."""
    board = boards.parse_board("9x6:0.03")
    base_T_ee, views = rig(board, 12, 1)
    residuals = {}
    for sigma in (0.1, 2.0):
        conv = check(board, base_T_ee, views, sigma)
        assert (conv.unit, conv.direction) == ("m", "as given (base_T_ee)")
        r = conv.residuals[conv.name]
        assert r[0] < 3 * conv.expected[0] and r[1] < 3 * conv.expected[1], (r, conv.expected)
        residuals[sigma] = r
        with pytest.raises(InputError, match="mispaired") as e:
            check(board, base_T_ee, views, sigma, order=[(i + 1) % 12 for i in range(12)])
        assert "\n" not in str(e.value)
    assert residuals[2.0][1] > FIT_RATIO * residuals[0.1][1]  # a fixed mm threshold would refuse one or the other
    # the convention is still found when the file is ee_T_base in mm
    dets, P = projected(board, views, 0.1)
    mats = {f"{i:04d}": E.inverse().matrix() for i, E in enumerate(base_T_ee)}
    for M in mats.values():
        M[:3, 3] *= 1000
    conv = choose_convention(mats, P, board_turns.pose_covariances(board, dets, P, K, np.zeros(4)), board)
    assert conv.name == "inverted (file holds ee_T_base), mm"
    np.testing.assert_allclose(apply_convention(mats["0003"], conv.unit, conv.direction).matrix(),
                               base_T_ee[3].matrix(), atol=1e-9)
    # forced as they are: used and checked, reported as forced, no warning against what was given
    forced = choose_convention(mats, P, board_turns.pose_covariances(board, dets, P, K, np.zeros(4)), board, "mm",
                               "ee_T_base")
    lines = "\n".join(convention_lines(forced, "mm", "ee_T_base", "--unit, --direction"))
    assert "using 'inverted (file holds ee_T_base), mm' (forced, and checked" in lines and "  ! " not in lines
    with pytest.raises(InputError, match="with unit m \\(forced\\).*but they do as 'inverted"):
        choose_convention(mats, P, board_turns.pose_covariances(board, dets, P, K, np.zeros(4)), board, "m")


def test_turned_board_resolved_or_refused():
    """An 8x6 checkerboard (the same turned by 180°) with every third detection numbered from the
    opposite corner: resolved against the robot's motion. Seen only straight from above, from one
    height, turned by exactly 0° or 90° about its normal, the motion cannot tell the two groups'
    turns apart (a 90° and a -90° turn have the same angle, and neither has pitch): refused, naming
    the images and the board and suggesting ChArUco, at import and in pattern.detect."""
    board = boards.parse_board("8x6:0.03")
    base_T_ee, views = rig(board, 12, 2)
    dets, P = projected(board, views, 0.1)
    flip = {f for k, f in enumerate(sorted(dets)) if k % 3 == 2}
    dets = {f: (uv[::-1].copy() if f in flip else uv, ids) for f, (uv, ids) in dets.items()}
    T = gtsam.Pose3(board_turns.turn_matrix(board, 1, 2))
    P = {f: p.compose(T) if f in flip else p for f, p in P.items()}
    mats = {f"{i:04d}": E.matrix() for i, E in enumerate(base_T_ee)}
    conv = choose_convention(mats, P, board_turns.pose_covariances(board, dets, P, K, np.zeros(4)), board)
    assert conv.turns.turned == sorted(flip) and conv.name == "as given (base_T_ee), m"
    assert conv.residuals[conv.name][0] < 3 * conv.expected[0]
    centre = boards.points(board)[:, :2].mean(0)
    down = []
    for k in range(8):  # straight above the board's centre, rolled by 0° or 90°, at heights and offsets
        R = gtsam.Rot3.Rz(np.pi / 2 * (k % 2))
        eye = np.r_[centre + 0.01 * np.array([k % 3, k % 4]), -0.4]
        down.append(gtsam.Pose3(R, eye).inverse())
    base_T_ee, views = rig(board, 8, 3, cam_T_boards=down)
    told = r"checkerboard 8x6 30 mm looks the same turned by 180 deg, and the robot's motion cannot tell which way " \
           r"it was seen in image\(s\) 0001, 0003, 0005, 0007: use a ChArUco board"
    with pytest.raises(InputError, match=told) as e:
        check(board, base_T_ee, views, 0.1)
    assert "\n" not in str(e.value)
    dets, P = projected(board, views, 0.1)
    found = [pattern.Detection(f, uv, P[f], 0.0, None) for f, (uv, _) in dets.items()]
    with pytest.raises(InputError, match="dataset.yaml: the " + told):
        board_turns.unturn_detections(board, found, {f"{i:04d}": E for i, E in enumerate(base_T_ee)}, K, np.zeros(4),
                                 "dataset.yaml")
