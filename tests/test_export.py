"""``export``: every format parsed back (XML, Python AST, YAML) rebuilds parent_T_child to 1e-9,
in both child conventions, with the sigmas in a comment."""

import ast
import json
import xml.etree.ElementTree as ET

import gtsam
import numpy as np
import pytest
import yaml

from calib3r_graph.cli import main
from calib3r_graph.io.export import FORMATS, export, rpy_fixed_xyz

SIGMA = {"rx_deg": 0.0151, "ry_deg": 0.0132, "rz_deg": 0.0213, "x_mm": 0.241, "y_mm": 0.172, "z_mm": 0.803}
SIGMA_MODEL = {"rx_deg": 0.011, "ry_deg": 0.009, "rz_deg": 0.017, "x_mm": 0.18, "y_mm": 0.12, "z_mm": 0.61}


def rpy_matrix(r, p, y):
    return gtsam.Rot3.Ypr(y, p, r).matrix()  # Rz(y) Ry(p) Rx(r)


def write_result(root, poses: dict, model=True):
    root.mkdir(parents=True, exist_ok=True)
    cams = {c: {"T_ee_cam": X.matrix().tolist(), "covariance": np.eye(6).tolist(), "sigma_ee_frame": SIGMA,
                **({"sigma_ee_frame_model": SIGMA_MODEL} if model else {})} for c, X in poses.items()}
    (root / "calibration.json").write_text(json.dumps({"format": "calib3r-calibration/1", "cameras": cams}))
    return root


def parse(fmt, text):
    """(parent, child, 4x4) from an export, read the way ROS tools read it."""
    T = np.eye(4)
    if fmt in ("urdf", "xacro"):
        root = ET.fromstring(text)
        if fmt == "xacro":
            ns = "{http://www.ros.org/wiki/xacro}"
            macro = root.find(f"{ns}macro")
            params = dict(p.split(":=") for p in macro.get("params").split())
            joint = macro.find("joint")
            sub = lambda s: s.replace("${parent}", params["parent"]).replace("${child}", params["child"])  # noqa: E731
        else:
            joint, sub = root.find("joint"), (lambda s: s)
        assert joint.get("type") == "fixed"
        origin = joint.find("origin")
        T[:3, 3] = [float(v) for v in origin.get("xyz").split()]
        T[:3, :3] = rpy_matrix(*(float(v) for v in origin.get("rpy").split()))
        return sub(joint.find("parent").get("link")), sub(joint.find("child").get("link")), T
    if fmt == "ros1-launch":
        node = ET.fromstring(text).find("node")
        assert (node.get("pkg"), node.get("type")) == ("tf2_ros", "static_transform_publisher")
        args = node.get("args").split()
        v = [float(a) for a in args[:7]]
        parent, child = args[7:]
    elif fmt == "ros2-launch":
        compile(text, "launch.py", "exec")
        call = next(n for n in ast.walk(ast.parse(text)) if isinstance(n, ast.Call)
                    and any(k.arg == "arguments" for k in n.keywords))
        args = ast.literal_eval(next(k.value for k in call.keywords if k.arg == "arguments"))
        kv = dict(zip(args[::2], args[1::2]))
        v = [float(kv[f"--{k}"]) for k in ("x", "y", "z", "qx", "qy", "qz", "qw")]
        parent, child = kv["--frame-id"], kv["--child-frame-id"]
    elif fmt == "tf-yaml":
        d = yaml.safe_load(text)
        tr, q = d["translation"], d["rotation"]
        v = [tr["x"], tr["y"], tr["z"], q["x"], q["y"], q["z"], q["w"]]
        parent, child = d["parent_frame"], d["child_frame"]
        np.testing.assert_allclose(rpy_matrix(*d["rpy_fixed_xyz"]), gtsam.Rot3.Quaternion(v[6], *v[3:6]).matrix(),
                                   atol=1e-12)
    else:
        d = yaml.safe_load(text)
        tr = d["transformation"]
        v = [tr[k] for k in ("x", "y", "z", "qx", "qy", "qz", "qw")]
        parent, child = d["parameters"]["robot_effector_frame"], d["parameters"]["tracking_base_frame"]
        assert d["parameters"]["eye_on_hand"] is True
    T[:3, 3] = v[:3]
    T[:3, :3] = gtsam.Rot3.Quaternion(v[6], v[3], v[4], v[5]).matrix()
    return parent, child, T


@pytest.mark.parametrize("fmt", FORMATS)
def test_every_format_rebuilds_ee_T_cam(tmp_path, fmt):
    rng = np.random.default_rng(4)
    poses = {"cam0": gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3) * 0.1),
             # pitch of exactly 90 degrees: URDF's rpy at gimbal lock
             "cam1": gtsam.Pose3(gtsam.Rot3.Ypr(0.3, np.pi / 2, -0.2), np.array([0.01, -0.02, 0.13]))}
    root = write_result(tmp_path / "res", poses)
    for cam, X in poses.items():
        optical = parse(fmt, export(root, fmt, "tool0", "cam_optical", cam))
        assert optical[:2] == ("tool0", "cam_optical")
        np.testing.assert_allclose(optical[2], X.matrix(), atol=1e-9)
        link = parse(fmt, export(root, fmt, "tool0", "cam_link", cam, "camera_link"))[2]
        # camera_link's x is the optical z (forward), its y the optical -x (left), its z the optical -y (up)
        R_opt = X.rotation().matrix()
        np.testing.assert_allclose(link[:3, :3], np.c_[R_opt[:, 2], -R_opt[:, 0], -R_opt[:, 1]], atol=1e-9)
        np.testing.assert_allclose(link[:3, 3], X.translation(), atol=1e-9)
    text = export(root, fmt, "tool0", "cam_optical", "cam0")
    assert "sigma_ee_frame: x 0.241 y 0.172 z 0.803 mm, rx 0.0151 ry 0.0132 rz 0.0213 deg" in text
    assert "sigma_ee_frame_model: x 0.180 y 0.120 z 0.610 mm" in text
    assert "z forward, x right, y down" in text


def test_rpy_is_fixed_axis_xyz():
    r, p, y = 0.3, -0.7, 2.1
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    Rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    np.testing.assert_allclose(rpy_fixed_xyz(Rz @ Ry @ Rx), (r, p, y), atol=1e-12)


def test_export_cli(tmp_path, capsys):
    from calib3r_graph.cli import EXPORT_FORMATS

    assert EXPORT_FORMATS == FORMATS  # the parser lists them without importing export.py
    X = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.01, -0.02, 1.57), np.array([0.0367, -0.027, 0.0928]))
    one = write_result(tmp_path / "one", {"cam0": X}, model=False)
    assert main(["export", str(one), "--format", "urdf", "--parent", "tool0", "--child", "cam"]) == 0
    out = capsys.readouterr().out
    np.testing.assert_allclose(parse("urdf", out)[2], X.matrix(), atol=1e-9)
    assert "sigma_ee_frame_model" not in out
    dst = tmp_path / "desc" / "hand_eye.launch.py"
    assert main(["export", str(one / "calibration.json"), "--format", "ros2-launch", "--parent", "tool0",
                 "--child", "cam", "--out", str(dst)]) == 0
    assert capsys.readouterr().out == "" and parse("ros2-launch", dst.read_text())[2] is not None
    assert [p.name for p in dst.parent.iterdir()] == ["hand_eye.launch.py"]  # no temporary left behind
    two = write_result(tmp_path / "two", {"cam0": X, "cam1": X})
    for argv, msg in [([str(two)], "the result has cameras cam0, cam1: choose one"),
                      ([str(two), "--camera", "cam7"], "no camera 'cam7'"),
                      ([str(tmp_path / "none")], "none: no such result"),
                      ([str(tmp_path)], "calibration.json: missing (run 'calib3r-graph solve' first)"),
                      ([str(one), "--child", "my camera"], "is not a frame name")]:
        base = ["export", "--format", "tf-yaml", "--parent", "tool0"] + (["--child", "cam"] if "--child" not in argv
                                                                         else [])
        assert main(base + argv) == 3
        err = capsys.readouterr().err
        assert msg in err and err.count("\n") == 1, err
