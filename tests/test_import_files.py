"""``import files``: every pose format read back exactly, intrinsics files of each tool, and
whole imports of rendered recordings (the simulator's checkerboard, a ChArUco rig) whose pose
direction and unit are found from the images."""

import json

import cv2
import gtsam
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from calib3r_graph.cli import main
from calib3r_graph.errors import InputError
from calib3r_graph.io import boards
from calib3r_graph.io.dataset import load_dataset, load_ground_truth, pose_from_dict
from calib3r_graph.io.intrinsics_files import read_intrinsics
from calib3r_graph.io.pose_files import column_names, parse_format, read_poses, to_matrix, to_numbers
from tests.test_boards import look_at, render_view

K = np.array([[600.0, 0, 322.0], [0, 600.0, 238.0], [0, 0, 1]])


def random_poses(n=5, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        M = np.eye(4)
        M[:3, :3] = Rotation.random(random_state=rng.integers(1 << 30)).as_matrix()
        M[:3, 3] = rng.uniform(-0.8, 0.8, 3)
        out.append(M)
    return out


def elementary(axis, a):
    c, s = np.cos(a), np.sin(a)
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def encode(M, fmt):
    t, R = M[:3, 3], Rotation.from_matrix(M[:3, :3])
    if fmt == "matrix":
        return M.ravel()
    if fmt == "xyz-quat-xyzw":
        return np.r_[t, R.as_quat()]
    if fmt == "xyz-quat-wxyz":
        return np.r_[t, np.roll(R.as_quat(), 1)]
    if fmt in ("xyz-rotvec", "visp"):
        return np.r_[t, R.as_rotvec()]
    if fmt == "xyz-euler:zyx:deg":  # KUKA A, B, C
        return np.r_[t, R.as_euler("ZYX", degrees=True)]
    if fmt == "xyz-euler:fixed-xyz:rad":  # ROS roll, pitch, yaw
        return np.r_[t, R.as_euler("xyz")]
    raise ValueError(fmt)


FORMATS = ["matrix", "xyz-quat-xyzw", "xyz-quat-wxyz", "xyz-rotvec", "visp", "xyz-euler:zyx:deg",
           "xyz-euler:fixed-xyz:rad"]


@pytest.mark.parametrize("fmt", FORMATS)
def test_pose_formats_read_back_exactly(tmp_path, fmt):
    poses = random_poses()
    lines = ["# exported by the robot", "x,y,z,a,b,c,d,e,f,g,h,i,j,k,l,m"]  # a comment and a header
    lines += [", ".join(f"{v:.15g}" for v in encode(M, fmt)) for M in poses]
    (tmp_path / "p.csv").write_text("\n".join(lines) + "\n")
    recs = read_poses(str(tmp_path / "p.csv"), parse_format(fmt))
    assert [r.number for r in recs] == [None] * 5
    for r, M in zip(recs, poses):
        np.testing.assert_allclose(r.matrix, M, atol=1e-12)
    # with a frame number first, one file per frame as .npy and .json
    (tmp_path / "n.txt").write_text("".join(f"{10 + k} " + " ".join(f"{v:.15g}" for v in encode(M, fmt)) + "\n"
                                            for k, M in enumerate(poses)))
    assert [r.number for r in read_poses(str(tmp_path / "n.txt"), parse_format(fmt))] == [10, 11, 12, 13, 14]
    (tmp_path / "per").mkdir()
    for k, M in enumerate(poses):
        if k % 2:
            np.save(tmp_path / "per" / f"pose_{k + 3}.npy", encode(M, fmt).reshape(4, 4) if fmt == "matrix"
                    else encode(M, fmt))
        else:
            (tmp_path / "per" / f"pose_{k + 3}.json").write_text(json.dumps({"pose": encode(M, fmt).tolist()}))
    recs = read_poses(str(tmp_path / "per"), parse_format(fmt))
    assert sorted(r.number for r in recs) == [3, 4, 5, 6, 7]
    for r in recs:
        np.testing.assert_allclose(r.matrix, poses[r.number - 3], atol=1e-12)


@pytest.mark.parametrize("fmt", FORMATS + ["xyz-euler:zyz:deg", "xyz-euler:fixed-xzx:rad"])
def test_a_pose_written_in_a_format_reads_back_to_the_same_matrix(fmt):
    """to_numbers (what live writes into next_poses.csv for a user's own pose format) is to_matrix's
    inverse: random poses, both matrix layouts, and the Euler angles' gimbal lock (middle angle at its
    limit, where the first and third angles turn about one axis)."""
    f = parse_format(fmt)
    poses = random_poses(20, seed=1)
    if f.euler:
        seq, deg = f.euler
        limit = (90.0, -90.0) if len(set(seq.lower())) == 3 else (0.0, 180.0)
        for i, b in enumerate(limit):
            poses[i][:3, :3] = Rotation.from_euler(seq, [25.0, b, -40.0], degrees=True).as_matrix()
    for layout in ("row-major", "column-major"):
        assert len(column_names(f, layout)) == f.count
        for M in poses:
            v = to_numbers(M, f, layout)
            assert v.shape == (f.count,)
            np.testing.assert_allclose(to_matrix(v, f, "p", layout), M, atol=1e-12)
    if fmt.startswith("xyz-quat"):  # one sign of q and -q
        assert all(to_numbers(M, f)[6 if fmt.endswith("xyzw") else 3] >= 0 for M in poses)
    assert column_names(parse_format("xyz-euler:zyx:deg")) == ["x", "y", "z", "a", "b", "c"]
    assert column_names(parse_format("matrix"), "column-major")[:5] == ["m00", "m10", "m20", "m30", "m01"]


def test_euler_conventions_and_visp_yaml(tmp_path):
    """KUKA's A, B, C (zyx) is R = Rz(A) Ry(B) Rx(C); fixed-xyz (ROS rpy) is R = Rz(y) Ry(p) Rx(r)."""
    a, b, c = 30.0, -20.0, 75.0
    (tmp_path / "k.txt").write_text(f"100 -200 300 {a} {b} {c}\n")
    R = read_poses(str(tmp_path / "k.txt"), parse_format("xyz-euler:zyx:deg"))[0].matrix[:3, :3]
    A, B, C = np.radians([a, b, c])
    np.testing.assert_allclose(R, elementary("z", A) @ elementary("y", B) @ elementary("x", C), atol=1e-12)
    R = read_poses(str(tmp_path / "k.txt"), parse_format("xyz-euler:fixed-xyz:deg"))[0].matrix[:3, :3]
    np.testing.assert_allclose(R, elementary("z", C) @ elementary("y", B) @ elementary("x", A), atol=1e-12)
    # ViSP's vpPoseVector::saveYAML, one file per frame (pose_fPe_N.yaml)
    M = random_poses(1)[0]
    (tmp_path / "visp").mkdir()
    v = encode(M, "visp")
    (tmp_path / "visp" / "pose_fPe_2.yaml").write_text("rows: 6\ncols: 1\ndata:\n"
                                                       + "".join(f"  - [{float(x)!r}]\n" for x in v))
    rec = read_poses(str(tmp_path / "visp" / "*.yaml"), parse_format("visp"))
    assert rec[0].number == 2
    np.testing.assert_allclose(rec[0].matrix, M, atol=1e-12)
    # a 4x4 over four lines (Tabb's layout)
    (tmp_path / "m.txt").write_text("\n".join(" ".join(f"{x:.15g}" for x in row) for row in M) + "\n")
    np.testing.assert_allclose(read_poses(str(tmp_path / "m.txt"), parse_format("matrix"))[0].matrix, M, atol=1e-12)


@pytest.mark.parametrize("fmt,line,msg", [
    ("xyz-quat-xyzw", "0 0 0 0.5 0.5 0.5 0.9", "quaternion is not unit"),
    ("xyz-rotvec", "0 0 0 1 2", "expected 6 numbers"),
    ("matrix", " ".join(["1"] * 16), "last row"),
    ("matrix", "2 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1", "not a rotation"),
    ("xyz-euler:zxx:deg", "0 0 0 1 2 3", "twice in a row"),
    ("xyz-euler:abc", "0", "unknown pose format"),
])
def test_bad_pose_files(tmp_path, fmt, line, msg):
    (tmp_path / "p.txt").write_text(line + "\n")
    with pytest.raises(InputError, match=msg) as e:
        read_poses(str(tmp_path / "p.txt"), parse_format(fmt))
    assert "\n" not in str(e.value)


def test_intrinsics_files(tmp_path):
    D = np.array([0.1, -0.2, 0.001, 0.002, 0.0])
    expect = (600.0, 601.0, 322.0, 238.0, 0.1, -0.2, 0.001, 0.002)
    Km = np.array([[600.0, 0, 322.0], [0, 601.0, 238.0], [0, 0, 1]])
    ros = {"image_width": 640, "image_height": 480, "camera_name": "cam",
           "camera_matrix": {"rows": 3, "cols": 3, "data": Km.ravel().tolist()}, "distortion_model": "plumb_bob",
           "distortion_coefficients": {"rows": 1, "cols": 5, "data": D.tolist()}}
    (tmp_path / "ros.yaml").write_text(yaml.safe_dump(ros))
    echo = {"header": {"frame_id": "cam"}, "height": 480, "width": 640, "distortion_model": "plumb_bob",
            "d": D.tolist(), "k": Km.ravel().tolist()}
    (tmp_path / "echo.yaml").write_text(yaml.safe_dump(echo))
    for suffix in ("yaml", "xml"):
        fs = cv2.FileStorage(str(tmp_path / f"cv.{suffix}"), cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", 640)
        fs.write("image_height", 480)
        fs.write("camera_matrix", Km)
        fs.write("distortion_coefficients", D.reshape(1, -1))
        fs.release()
    for name in ("ros.yaml", "echo.yaml", "cv.yaml", "cv.xml"):
        (intr,) = read_intrinsics(tmp_path / name)
        np.testing.assert_allclose(intr.params, expect, rtol=1e-12, err_msg=name)
        assert (intr.width, intr.height) == (640, 480)
    kalibr = {f"cam{j}": {"camera_model": "pinhole", "intrinsics": [600.0 + j, 601.0, 322.0, 238.0],
                          "distortion_model": "radtan", "distortion_coeffs": D[:4].tolist(),
                          "resolution": [640, 480], "rostopic": f"/cam{j}/image_raw"} for j in range(2)}
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump(kalibr))
    cams = read_intrinsics(tmp_path / "camchain.yaml")
    assert [c.params[0] for c in cams] == [600.0, 601.0] and cams[1].params[4:] == expect[4:]
    # the whole OpenCV model is kept: k3 (plumb_bob's fifth), the rational k4-k6; thin prism refused
    for coeffs, dist in [([0.1, -0.2, 0.001, 0.002, 0.05], 5), ([0.1, -0.2, 0.001, 0.002, 0.05, 0.01, 0, 0], 8),
                         ([0.1, -0.2, 0.001, 0.002, 0.0, 0.0, 0.0, 0.0], 4)]:
        ros["distortion_coefficients"]["data"] = coeffs
        (tmp_path / "k3.yaml").write_text(yaml.safe_dump(ros))
        assert read_intrinsics(tmp_path / "k3.yaml")[0].params == (*expect[:4], *coeffs[:dist])
    ros["distortion_coefficients"]["data"] = [0.1, -0.2, 0.001, 0.002, 0.05, 0, 0, 0, 1e-3, 0, 0, 0]
    (tmp_path / "k3.yaml").write_text(yaml.safe_dump(ros))
    with pytest.raises(InputError, match="thin-prism"):
        read_intrinsics(tmp_path / "k3.yaml")
    kalibr["cam0"]["distortion_model"] = "equidistant"
    (tmp_path / "fish.yaml").write_text(yaml.safe_dump(kalibr))
    with pytest.raises(InputError, match="fisheye"):
        read_intrinsics(tmp_path / "fish.yaml")
    (tmp_path / "junk.yaml").write_text("a: 1\n")
    with pytest.raises(InputError, match="not a ROS camera_info"):
        read_intrinsics(tmp_path / "junk.yaml")


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    from calib3r_graph.simulate import SimOptions, simulate

    return simulate(tmp_path_factory.mktemp("r") / "d", SimOptions(seed=51, frames=8, images=True, pattern=True),
                    progress=False)


def true_poses(root):
    return {f: pose_from_dict(d) for f, d in load_ground_truth(root)["base_T_ee_true"].items()}


def assert_poses(dst, truth, atol=1e-6):
    ds = load_dataset(dst)
    assert len(ds.frames) == len(truth)
    for (f, E), (g, T) in zip(sorted(ds.base_T_ee.items()), sorted(truth.items())):
        np.testing.assert_allclose(E.matrix(), T.matrix(), atol=atol)
    return ds


@pytest.mark.slow
def test_inverted_millimetre_matrices_are_found_from_the_images(rendered, tmp_path, capsys):
    raw = tmp_path / "raw"
    raw.mkdir()
    lines = []
    for i, (f, E) in enumerate(sorted(true_poses(rendered).items())):
        M = E.inverse().matrix()  # the file holds ee_T_base in mm: both wrong for the default
        M[:3, 3] *= 1000
        lines.append(" ".join(f"{x:.9f}" for x in M.ravel()))
        cv2.imwrite(str(raw / f"shot_{i + 1}.bmp"), cv2.imread(str(rendered / "images" / "cam0" / f"{f}.png")))
    (raw / "poses.txt").write_text("\n".join(lines) + "\n")
    dst = tmp_path / "ds"
    assert main(["import", "files", str(dst), "--images", str(raw / "*.bmp"), "--poses", str(raw / "poses.txt"),
                 "--pose-format", "matrix", "--board", "9x6:0.03"]) == 0
    out = capsys.readouterr().out
    assert "* inverted (file holds ee_T_base), mm" in out and "matched to poses in sorted order" in out
    ds = assert_poses(dst, true_poses(rendered))
    assert ds.pattern == {"type": "checkerboard", "inner_corners": [9, 6], "square_size": 0.03}
    true_K = load_dataset(rendered).cameras["cam0"].K
    np.testing.assert_allclose(np.diag(ds.cameras["cam0"].K)[:2], np.diag(true_K)[:2], rtol=0.015)
    assert (dst / "images" / "cam0" / "0000.png").is_file()
    # An intrinsics file instead of calibrating; quaternions in mm with a frame column; the
    # images named by frame number with gaps.
    numbered = tmp_path / "numbered"
    numbered.mkdir()
    rows = ["frame x y z qw qx qy qz"]
    for i, (f, E) in enumerate(sorted(true_poses(rendered).items())):
        n = 3 * i + 5
        cv2.imwrite(str(numbered / f"frame_{n:05d}.png"), cv2.imread(str(rendered / "images" / "cam0" / f"{f}.png")))
        rows.append(f"{n} " + " ".join(f"{v:.12g}" for v in np.r_[E.translation() * 1e3,
                                                                   np.roll(Rotation.from_matrix(
                                                                       E.rotation().matrix()).as_quat(), 1)]))
    (numbered / "poses.txt").write_text("\n".join(rows[:1] + rows[:0:-1]) + "\n")  # any order in the file
    Kt = true_K
    (numbered / "cam.yaml").write_text(yaml.safe_dump({
        "image_width": 640, "image_height": 480, "distortion_model": "plumb_bob",
        "camera_matrix": {"rows": 3, "cols": 3, "data": Kt.ravel().tolist()},
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.0] * 5}}))
    dst2 = tmp_path / "ds2"
    assert main(["import", "files", str(dst2), "--images", str(numbered), "--poses", str(numbered / "poses.txt"),
                 "--pose-format", "xyz-quat-wxyz", "--unit", "mm", "--intrinsics", str(numbered / "cam.yaml"),
                 "--board", "9x6:0.03"]) == 0
    out = capsys.readouterr().out
    assert "* as given (base_T_ee), mm" in out and "matched to poses by number" in out
    ds2 = assert_poses(dst2, true_poses(rendered), atol=1e-6)
    assert ds2.frames == [f"{3 * i + 5:04d}" for i in range(8)]
    np.testing.assert_allclose(ds2.cameras["cam0"].K, Kt)


@pytest.mark.slow
def test_charuco_recording_with_kuka_poses(tmp_path, capsys):
    """A ChArUco board (dictionary not given) seen by a camera on a KUKA reporting X, Y, Z in mm
    and A, B, C in degrees: intrinsics calibrated from the partial views, poses checked."""
    rng = np.random.default_rng(5)
    board = boards.parse_board("charuco:9x6:0.03:0.022:DICT_5X5_100")
    ee_T_cam = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.01, 0.02, -np.pi / 2), np.array([-0.03, 0.05, 0.08]))
    base_T_board = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.array([0.6, -0.1, 0.02]))
    raw = tmp_path / "raw"
    raw.mkdir()
    centre = boards.points(board)[:, :2].mean(0)
    lines, truth = [], {}
    for i in range(9):
        cam_T_board = look_at(rng, rng.uniform(0.3, 0.45), target=centre + rng.uniform(-0.05, 0.05, 2), tilt_deg=30)
        E = base_T_board.compose(cam_T_board.inverse()).compose(ee_T_cam.inverse())
        truth[f"{i:04d}"] = E
        cv2.imwrite(str(raw / f"img{i:03d}.png"), render_view(board, cam_T_board, rng=rng))
        abc = Rotation.from_matrix(E.rotation().matrix()).as_euler("ZYX", degrees=True)
        lines.append(" ".join(f"{v:.10f}" for v in np.r_[E.translation() * 1e3, abc]))
    (raw / "kuka.txt").write_text("\n".join(lines) + "\n")
    dst = tmp_path / "ds"
    assert main(["import", "files", str(dst), "--images", str(raw), "--poses", str(raw / "kuka.txt"),
                 "--pose-format", "xyz-euler:zyx:deg", "--unit", "mm", "--board", "charuco:9x6:0.03:0.022"]) == 0
    out = capsys.readouterr().out
    assert "* as given (base_T_ee), mm" in out and "!" not in out
    ds = assert_poses(dst, truth, atol=1e-8)
    assert ds.pattern["type"] == "charuco" and ds.pattern["dictionary"] == "DICT_5X5_50"
    np.testing.assert_allclose(np.diag(ds.cameras["cam0"].K)[:2], [600.0, 600.0], rtol=0.01)
    np.testing.assert_allclose(ds.cameras["cam0"].K[:2, 2], [322.0, 238.0], atol=5.0)
    # The same recording in RWHE-Calib's layout: `import rwhe` takes the ChArUco spec too.
    rwhe = tmp_path / "rwhe"
    rwhe.mkdir()
    for i, (f, E) in enumerate(sorted(truth.items()), 1):
        (rwhe / f"{i:02d}.png").write_bytes((raw / f"img{i - 1:03d}.png").read_bytes())
    (rwhe / "RobotPosesVec.txt").write_text("".join(" ".join(f"{x:.12f}" for x in E.matrix().ravel()) + "\n"
                                                    for _, E in sorted(truth.items())))
    (rwhe / "squaresize.txt").write_text("30mm")
    assert main(["import", "rwhe", str(rwhe), str(tmp_path / "rw"), "--board", "charuco:9x6:0.03:0.022"]) == 0
    assert "* as given (base_T_ee), m " in capsys.readouterr().out
    assert load_dataset(tmp_path / "rw").pattern["type"] == "charuco"
    assert_poses(tmp_path / "rw", truth, atol=1e-8)


def test_import_files_errors(tmp_path, capsys):
    raw = tmp_path / "raw"
    raw.mkdir()
    img = np.full((48, 64, 3), 128, np.uint8)
    for i in range(4):
        cv2.imwrite(str(raw / f"{i}.png"), img)
    base = ["import", "files", str(tmp_path / "o"), "--images", str(raw), "--poses", str(raw / "p.txt"),
            "--pose-format", "xyz-quat-xyzw"]
    cases = [(4, base + ["--intrinsics", str(raw / "none.yaml")], "none.yaml: no such intrinsics file"),
             (4, base, "give the cameras' intrinsics"),
             (4, base + ["--board", "9x6"], "give the square size"),
             (4, base + ["--board", "9x6:0.03"], "the 9x6 chessboard is found in fewer than 3 images"),
             (3, base + ["--board", "charuco:5x5:0.03:0.02"], "4 images but 3 poses, matched by the number in the "
                                                               "file names: frame(s) 3 have no pose")]
    for n, argv, msg in cases:
        (raw / "p.txt").write_text("".join(f"{i} 0 0 0 0 0 0 1\n" for i in range(n)))
        assert main(argv) == 3
        err = capsys.readouterr().err
        assert msg in err and err.count("\n") == 1, err
    (raw / "p.txt").write_text("".join("0 0 0 0 0 0 1\n" for _ in range(3)))  # no frame numbers: by order
    assert main(base + ["--board", "9x6:0.03"]) == 3
    assert "4 images but 3 poses (matched in sorted order" in capsys.readouterr().err
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "keep.txt").write_text("user data")
    assert main(base + ["--board", "9x6:0.03"]) == 3
    assert "exists and is not empty" in capsys.readouterr().err
