"""The files users' recordings come with, each written here: Franka's per-frame ``data.json``
(``O_T_EE``, column- or row-major) in per-frame folders, ViSP's ``camera.xml``, intrinsics in an
``.npz``, and the full OpenCV lens model (k3, rational k4-k6) from import to pattern-ba on a
rendered scene."""

import json

import cv2
import gtsam
import numpy as np
import pytest
import yaml

from calib3r_graph.cli import main
from calib3r_graph.errors import InputError
from calib3r_graph.io import boards
from calib3r_graph.io.dataset import load_dataset, opencv_camera, write_dataset_yaml
from calib3r_graph.io.intrinsics_files import read_intrinsics
from calib3r_graph.io.pose_files import describe, parse_format, read_poses
from tests.test_boards import look_at, render_view
from tests.test_import_files import random_poses

SIZE = (640, 480)
MATRIX = parse_format("matrix")
EE_T_CAM = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.02, -0.03, np.pi / 2), np.array([0.04, -0.03, 0.09]))
BASE_T_BOARD = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.array([0.5, 0.1, 0.0]))  # face up on the table


def rig(n, K, dist, seed=11, pad=200, corners=False):
    """Images of a 9x6 board from ``n`` flange poses through OpenCV's lens model ``dist``:
    ([image], [base_T_ee]). Each pixel looks up the pinhole image (rendered on a padded canvas)
    at its undistorted position. ``corners``: the board seen in a corner of the image (where the
    higher lens terms act) rather than in the middle."""
    rng = np.random.default_rng(seed)
    board = boards.parse_board("9x6:0.03")
    centre = boards.points(board)[:, :2].mean(0)
    uv = np.stack(np.meshgrid(np.arange(SIZE[0]), np.arange(SIZE[1])), -1).reshape(-1, 1, 2).astype(np.float64)
    ideal = cv2.undistortPointsIter(uv, K, np.asarray(dist, float), None, K,
                                    (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10))
    ideal = ideal.reshape(SIZE[1], SIZE[0], 2).astype(np.float32) + pad
    Kp = K.copy()
    Kp[:2, 2] += pad
    images, poses = [], []
    for _ in range(n):
        if corners:  # 0.4-0.5 m away, the camera's axis 0.15 m, 0.09 m off the board's centre
            target, distance = centre + rng.choice([-1, 1], 2) * [0.15, 0.09], rng.uniform(0.4, 0.5)
        else:
            target, distance = centre + rng.uniform(-0.01, 0.01, 2), rng.uniform(0.3, 0.42)
        cam_T_board = look_at(rng, distance, target=target, tilt_deg=15 if corners else 30)
        poses.append(BASE_T_BOARD.compose(cam_T_board.inverse()).compose(EE_T_CAM.inverse()))
        big = render_view(board, cam_T_board, K=Kp, size=(SIZE[0] + 2 * pad, SIZE[1] + 2 * pad), rng=rng)
        images.append(cv2.remap(big, ideal[..., 0], ideal[..., 1], cv2.INTER_LINEAR, borderValue=150))
    return images, poses


def visp_xml(cameras) -> str:
    """A vpXmlParserCamera file: cameras = [(name, (w, h), px, py, u0, v0, kud or None)]."""
    out = ['<?xml version="1.0"?>', "<root>"]
    for name, (w, h), px, py, u0, v0, kud in cameras:
        out += ["  <camera>", f"    <name>{name}</name>", f"    <image_width>{w}</image_width>",
                f"    <image_height>{h}</image_height>", "    <model>",
                "      <type>perspectiveProjWithoutDistortion</type>",
                f"      <px>{px + 3}</px><py>{py + 3}</py><u0>{u0}</u0><v0>{v0}</v0>", "    </model>"]
        if kud is not None:
            out += ["    <model>", "      <type>perspectiveProjWithDistortion</type>",
                    f"      <px>{px}</px><py>{py}</py><u0>{u0}</u0><v0>{v0}</v0>",
                    f"      <kud>{kud}</kud><kdu>{-kud}</kdu>", "    </model>"]
        out += ["  </camera>"]
    return "\n".join(out + ["</root>"]) + "\n"


def franka_state(M, column_major=True, nested=False) -> dict:
    """A franky/libfranka robot state: several 16-number entries, the flange under O_T_EE."""
    flat = lambda A: (A.T if column_major else A).ravel().tolist()  # noqa: E731
    state = {"O_T_EE": flat(M), "F_T_EE": flat(np.eye(4)), "EE_T_K": flat(np.eye(4)), "q": [0.1] * 7,
             "robot_mode": "idle"}
    return {"time": 1.5, "robot": state} if nested else state


def test_franka_json_keys_and_layouts(tmp_path):
    poses = random_poses(4, seed=3)
    for k, M in enumerate(poses):
        (tmp_path / f"state_{k}.json").write_text(json.dumps(franka_state(M)))
    recs = read_poses(str(tmp_path / "state_*.json"), MATRIX)  # no --pose-key: the known key, column-major
    for r, M in zip(recs, poses):
        np.testing.assert_allclose(r.matrix, M, atol=1e-12)
    assert "'O_T_EE' (a known pose key)" in describe(recs) and "column-major" in describe(recs)
    # nested and row-major, named with --pose-key; one list of states in one YAML file
    (tmp_path / "all.yaml").write_text(yaml.safe_dump([franka_state(M, False, True) for M in poses]))
    recs = read_poses(str(tmp_path / "all.yaml"), MATRIX, "robot.O_T_EE")
    for r, M in zip(recs, poses):
        np.testing.assert_allclose(r.matrix, M, atol=1e-12)
    assert "row-major" in describe(recs) and "--pose-key" in describe(recs)
    # one 16-number entry of any name is taken, and said
    (tmp_path / "one.json").write_text(json.dumps({"flange": poses[0].ravel().tolist(), "q": [0.0] * 7}))
    assert "'flange' (the only entry of 16 numbers)" in describe(read_poses(str(tmp_path / "one.json"), MATRIX))
    bad = [({"F_T_EE": [0.0] * 16, "EE_T_K": [0.0] * 16}, None, "2 entries of 16 numbers.*F_T_EE \\(16 numbers\\)"),
           (franka_state(poses[0]), "O_T_EE_d", "no key 'O_T_EE_d'.*keys found: O_T_EE"),
           ({"O_T_EE": [1.0] * 16}, None, "last row of a 4x4 pose must be 0 0 0 1")]
    for content, key, msg in bad:
        (tmp_path / "bad.json").write_text(json.dumps(content))
        with pytest.raises(InputError, match=msg) as e:
            read_poses(str(tmp_path / "bad.json"), MATRIX, key)
        assert "\n" not in str(e.value) and "bad.json" in str(e.value)
    (tmp_path / "p.txt").write_text(" ".join(map(str, poses[0].ravel())) + "\n")
    with pytest.raises(InputError, match="p.txt: --pose-key 'O_T_EE' names an entry of a JSON or YAML file"):
        read_poses(str(tmp_path / "p.txt"), MATRIX, "O_T_EE")
    (tmp_path / "mixed.json").write_text(json.dumps([franka_state(poses[0]), franka_state(poses[1], False)]))
    with pytest.raises(InputError, match="column-major .* row-major: one layout for all"):
        read_poses(str(tmp_path / "mixed.json"), MATRIX)


def test_visp_camera_xml_and_npz(tmp_path):
    (tmp_path / "camera.xml").write_text(visp_xml([("Camera", (640, 480), 605.2, 604.8, 321.5, 239.25, -0.08),
                                                   ("Camera", (1280, 960), 1210.4, 1209.6, 643.0, 478.5, None),
                                                   ("Webcam", (640, 480), 500.0, 501.0, 320.0, 240.0, None)]))
    with pytest.raises(InputError, match="3 ViSP cameras among the 3 in it .*'Webcam'.*: name one with --camera-name"):
        read_intrinsics(tmp_path / "camera.xml")
    with pytest.raises(InputError, match="2 ViSP cameras for 640x480 images among the 3"):
        read_intrinsics(tmp_path / "camera.xml", size=(640, 480))
    with pytest.raises(InputError, match="no ViSP cameras named 'Kinect' among the 3"):
        read_intrinsics(tmp_path / "camera.xml", "Kinect")
    (intr,) = read_intrinsics(tmp_path / "camera.xml", "Camera", (640, 480))  # ViSP's k_ud is OpenCV's k1
    assert intr.params == (605.2, 604.8, 321.5, 239.25, -0.08, 0.0, 0.0, 0.0) and (intr.width, intr.height) == SIZE
    (intr,) = read_intrinsics(tmp_path / "camera.xml", "Camera", (1280, 960))
    assert intr.params == (1213.4, 1212.6, 643.0, 478.5, 0.0, 0.0, 0.0, 0.0)  # its only model: px + 3
    assert read_intrinsics(tmp_path / "camera.xml", "Webcam")[0].params[:2] == (503.0, 504.0)
    # ViSP's projection: u = u0 + px x (1 + kud r^2) is OpenCV's with k1 = kud
    x = np.array([[0.3, -0.2, 1.0]])
    uv = cv2.projectPoints(x, np.zeros(3), np.zeros(3), read_intrinsics(tmp_path / "camera.xml", "Camera", SIZE)[0].K,
                           np.array([-0.08, 0, 0, 0]))[0].ravel()
    np.testing.assert_allclose(uv, [321.5 + 605.2 * 0.3 * (1 - 0.08 * 0.13), 239.25 - 604.8 * 0.2 * (1 - 0.08 * 0.13)])
    K = np.array([[600.0, 0, 320], [0, 601, 240], [0, 0, 1]])
    for kk, kd in [("K", "dist"), ("camera_matrix", "distortion_coefficients"), ("mtx", "D")]:
        np.savez(tmp_path / "cam.npz", **{kk: K, kd: np.array([[0.1, -0.2, 0.0, 0.001, -0.0236]])})
        (intr,) = read_intrinsics(tmp_path / "cam.npz")
        assert intr.params == (600.0, 601.0, 320.0, 240.0, 0.1, -0.2, 0.0, 0.001, -0.0236)
    np.savez(tmp_path / "other.npz", intrinsics=K)
    (tmp_path / "junk.xml").write_text("<root><camera><name>a")
    (tmp_path / "dae.xml").write_text("<COLLADA/>")
    (tmp_path / "blob.bin").write_bytes(bytes(range(256)))
    for name, msg in [("other.npz", "needs K or camera_matrix or mtx.*it holds intrinsics"),
                      ("junk.xml", "not valid XML"), ("dae.xml", "root <COLLADA>"), ("blob.bin", "not a text file")]:
        with pytest.raises(InputError, match=msg) as e:
            read_intrinsics(tmp_path / name)
        assert "accepted: ROS camera_info YAML, OpenCV FileStorage YAML/XML, Kalibr" in str(e.value)
        assert "ViSP camera.xml, .npz with K and dist" in str(e.value) and "\n" not in str(e.value)


def test_import_franka_folders_with_visp_intrinsics(tmp_path, capsys):
    """pose_NN/image.png beside pose_NN/data.json (O_T_EE column-major), listed in an order that is
    neither sorted by name nor by number; the intrinsics in ViSP's camera.xml with distortion."""
    K = np.array([[600.0, 0, 322.0], [0, 600.0, 238.0], [0, 0, 1]])
    kud = -0.12
    numbers = [3, 7, 8, 10, 2, 11]
    images, poses = rig(len(numbers), K, [kud, 0, 0, 0])
    rec = tmp_path / "recording"
    for n, img, E in zip(numbers, images, poses):  # created in this order: not sorted by name nor number
        folder = rec / (f"pose_{n:02d}" if n != 2 else "pose_2")
        folder.mkdir(parents=True)
        cv2.imwrite(str(folder / "image.png"), img)
        (folder / "data.json").write_text(json.dumps(franka_state(E.matrix())))
    (tmp_path / "camera.xml").write_text(visp_xml([("Camera", SIZE, 600.0, 600.0, 322.0, 238.0, kud)]))
    dst = tmp_path / "ds"
    assert main(["import", "files", str(dst), "--images", str(rec / "pose_*" / "image.png"),
                 "--poses", str(rec / "pose_*" / "data.json"), "--pose-key", "O_T_EE",
                 "--intrinsics", str(tmp_path / "camera.xml"), "--board", "9x6:0.03"]) == 0
    out = capsys.readouterr().out
    assert "matched to poses by number" in out and "column-major" in out and "'O_T_EE'" in out
    ds = load_dataset(dst)
    assert ds.frames == [f"{n:04d}" for n in sorted(numbers)]
    for n, E in zip(numbers, poses):
        np.testing.assert_allclose(ds.base_T_ee[f"{n:04d}"].matrix(), E.matrix(), atol=1e-9)
        assert (dst / "images" / "cam0" / f"{n:04d}.png").read_bytes() == \
            (rec / (f"pose_{n:02d}" if n != 2 else "pose_2") / "image.png").read_bytes()
    assert ds.cameras["cam0"].params == (600.0, 600.0, 322.0, 238.0, kud, 0.0, 0.0, 0.0)
    frames = ds.meta["source"]["frames"]  # the map from the user's files to the frame ids
    assert frames["0002"] == {"cam0": str(rec / "pose_2" / "image.png"), "pose": str(rec / "pose_2" / "data.json")}
    # the same folders given as one folder: searched one level down
    assert main(["import", "files", str(tmp_path / "ds2"), "--images", str(rec), "--poses", str(rec),
                 "--intrinsics", str(tmp_path / "camera.xml"), "--pose-format", "matrix"]) == 0
    out = capsys.readouterr().out
    assert "'O_T_EE' (a known pose key)" in out and "no board given: the poses are taken as base_T_ee in m" in out
    meta = yaml.safe_load((tmp_path / "ds2" / "dataset.yaml").read_text())
    assert "no board given" in meta["source"]["pose_convention"] and "no board seen" not in str(meta)
    assert load_dataset(tmp_path / "ds2").frames == ds.frames
    # an XML that OpenCV cannot read is a one-line error naming the formats, exit 3 (not a crash)
    (tmp_path / "camera.xml").write_text("<root><camera>")
    assert main(["import", "files", str(tmp_path / "ds3"), "--images", str(rec), "--poses", str(rec),
                 "--intrinsics", str(tmp_path / "camera.xml"), "--pose-key", "O_T_EE"]) == 3
    err = capsys.readouterr().err
    assert "camera.xml: not valid XML" in err and "accepted:" in err and err.count("\n") == 1


def test_full_opencv_camera_model(tmp_path):
    """FULL_OPENCV in dataset.yaml: Camera.dist is what OpenCV takes (5 or 8 coefficients), the
    undistortion maps follow it, and the pattern factor's Jacobians hold with 12 intrinsics."""
    from calib3r_graph.frontends.common import undistort_maps
    from factors.pattern import PatternMeasurement, make_pattern_factor, pattern_error
    from tests.test_factors import check_factor

    K = np.array([[460.0, 0, 318], [0, 461, 245], [0, 0, 1]])
    five = opencv_camera("cam0", SIZE, K, [-0.054, 0.065, -7e-4, 3e-4, -0.0236])
    eight = opencv_camera("cam1", SIZE, K, [-0.054, 0.065, -7e-4, 3e-4, -0.0236, 0.01, 0.002, 0.0])
    assert (five.model, len(five.params), len(five.dist)) == ("FULL_OPENCV", 12, 5)
    assert (eight.model, len(eight.dist)) == ("FULL_OPENCV", 8)
    assert opencv_camera("cam2", SIZE, K, [0.1, 0, 0, 0, 0.0]).model == "OPENCV"
    root = tmp_path / "d"
    (root / "images" / "cam0").mkdir(parents=True)
    (root / "robot_poses.csv").write_text("frame,x,y,z,qx,qy,qz,qw\n0000,0,0,0,0,0,0,1\n")
    write_dataset_yaml(root, [five, eight])
    ds = load_dataset(root)
    assert ds.cameras["cam0"] == five and ds.cameras["cam1"].dist.tolist() == list(eight.params[4:])
    # the undistortion map sends each ideal pixel to where the lens model puts it
    mx, my = undistort_maps(five)
    u, v = 600, 60  # an ideal (pinhole) pixel near the corner, and its ray
    p = (np.linalg.inv(K) @ [u, v, 1.0])[None]
    raw = cv2.projectPoints(p, np.zeros(3), np.zeros(3), K, five.dist)[0].ravel()
    np.testing.assert_allclose([mx[v, u], my[v, u]], raw, atol=0.01)
    without_k3 = cv2.projectPoints(p, np.zeros(3), np.zeros(3), K, five.dist[:4])[0].ravel()
    assert np.linalg.norm(raw - without_k3) > 1.0  # k3 is used
    # Jacobians of the pattern factor with the rational model as a variable
    rng = np.random.default_rng(3)
    corners = np.c_[np.mgrid[0:4, 0:3].reshape(2, -1).T * 0.05, np.zeros(12)]
    vals = gtsam.Values()
    vals.insert(0, gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.05), np.array([0, 0, 0.3])))
    vals.insert(1, gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.05), rng.normal(size=3) * 0.02))
    vals.insert(2, np.array(eight.params) + np.r_[np.zeros(9), 0.0, 0.0, 0.003])
    m = PatternMeasurement(corners, rng.uniform(200, 400, size=(12, 2)), np.zeros(12))
    check_factor(lambda fac, v, H: pattern_error(m, fac, v, H), make_pattern_factor(m, [0, 1, 2]), vals, atol=1e-4)
    # and the factor with fixed intrinsics projects as OpenCV does
    m = PatternMeasurement(corners, np.zeros((12, 2)), np.array(eight.params), sigma_px=1.0)
    pose = vals.atPose3(0).between(vals.atPose3(1)).inverse()  # cam_T_board
    Q = np.array([pose.transformFrom(c) for c in corners])
    ref = cv2.projectPoints(Q, np.zeros(3), np.zeros(3), K, eight.dist)[0].reshape(-1)
    np.testing.assert_allclose(make_pattern_factor(m, [0, 1]).unwhitenedError(vals), ref, atol=1e-6)


def test_realsense_k3_recording_gives_the_right_hand_eye(tmp_path, capsys):
    """A factory 5-coefficient plumb_bob model (k3 = -0.0236, as a RealSense reports it) on a wide
    640x480 camera, the board seen in the image's corners, where k3 moves it by 0.4-3 px: imported
    with --board, then PnP, park and pattern-ba on the imported dataset land within a millimetre of
    the true hand-eye. It was refused before ('recalibrate with k3 fixed at 0'); with k3 dropped the
    PnP residual is 0.22 px and park is 9 mm, 0.6 deg off."""
    from calib3r_graph.evaluation.pattern import detect, opencv_hand_eye, pattern_ba
    from calib3r_graph.solver.graph import NoiseOptions

    K = np.array([[460.0, 0, 318.0], [0, 461.0, 245.0], [0, 0, 1]])
    dist = [-0.054, 0.065, -7e-4, 3e-4, -0.0236]
    images, poses = rig(9, K, dist, seed=5, corners=True)
    raw = tmp_path / "raw"
    raw.mkdir()
    lines = []
    for i, (img, E) in enumerate(zip(images, poses)):
        cv2.imwrite(str(raw / f"color_{i:03d}.png"), img)
        lines.append(" ".join(f"{v:.12g}" for v in E.matrix().ravel()))
    (raw / "poses.txt").write_text("\n".join(lines) + "\n")
    (raw / "color.yaml").write_text(yaml.safe_dump({
        "image_width": 640, "image_height": 480, "distortion_model": "plumb_bob",
        "camera_matrix": {"rows": 3, "cols": 3, "data": K.ravel().tolist()},
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": dist}}))
    dst = tmp_path / "ds"
    assert main(["import", "files", str(dst), "--images", str(raw), "--poses", str(raw / "poses.txt"),
                 "--pose-format", "matrix", "--intrinsics", str(raw / "color.yaml"), "--board", "9x6:0.03"]) == 0
    capsys.readouterr()
    ds = load_dataset(dst)
    cam = ds.cameras["cam0"]
    assert cam.model == "FULL_OPENCV" and cam.dist.tolist() == dist
    dets = detect(ds, "cam0")
    assert len(dets) >= 7 and max(d.reprojection_px for d in dets) < 0.1  # the corner noise: 0.04 px
    init = {"cam0": opencv_hand_eye(ds, dets, "park")}
    res = pattern_ba(ds, {"cam0": dets}, NoiseOptions(), init, estimate_board_scale=False)
    assert len(res.intrinsics["cam0"]) == 12 and res.intrinsics["cam0"][8] == pytest.approx(-0.0236, abs=1e-5)
    for X in (init["cam0"], res.ee_T_cam["cam0"]):
        err = X.between(EE_T_CAM)
        assert np.linalg.norm(err.translation()) < 1.5e-3
        assert np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(err.rotation()))) < 0.15
