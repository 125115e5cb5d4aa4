"""``export``: a solve result's ee_T_cam in the formats a robot description takes.

The transform written is ``parent_T_child``: ``--parent`` is the flange link the camera is
mounted on (the ee frame of the robot poses), ``--child`` the camera frame it creates.

* ``optical`` child (default): the frame calib3r-graph solves for: z forward, x right, y down
  (REP 103/105 ``*_optical_frame``).
* ``camera_link`` child: the body frame, x forward, y left, z up:
  ``ee_T_link = ee_T_cam · optical_T_link`` with ``optical_T_link`` = rpy (-90°, 0, -90°)⁻¹.

Rotations are written as quaternions (x, y, z, w) where the format allows, and as URDF's rpy
otherwise: fixed axes X, Y, Z in that order, R = Rz(yaw)·Ry(pitch)·Rx(roll). Every output
carries the 1-sigma of ee_T_cam (per ee axis, from calibration.json) as a comment.
"""

import json
import re
from pathlib import Path

import gtsam
import numpy as np

from calib3r_graph.errors import InputError
from calib3r_graph.io.dataset import ee_T_cam_by_camera

FORMATS = ("urdf", "xacro", "ros2-launch", "ros1-launch", "tf-yaml", "easy-handeye")
# optical_T_link: the camera_link body frame (x forward, y left, z up) in optical axes.
OPTICAL_T_LINK = np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1.0]])
CONVENTIONS = {"optical": "optical frame: z forward, x right, y down (REP 103/105)",
               "camera_link": "camera_link body frame: x forward, y left, z up (REP 103)"}


def rpy_fixed_xyz(R: np.ndarray) -> tuple:
    """URDF rpy of a rotation: R = Rz(yaw) Ry(pitch) Rx(roll), pitch in [-90°, 90°]."""
    pitch = np.arctan2(-R[2, 0], np.hypot(R[0, 0], R[1, 0]))
    if np.hypot(R[0, 0], R[1, 0]) < 1e-9:  # gimbal lock: yaw and roll share one angle; put it in roll
        return float(np.arctan2(-R[1, 2], R[1, 1])), float(pitch), 0.0
    return float(np.arctan2(R[2, 1], R[2, 2])), float(pitch), float(np.arctan2(R[1, 0], R[0, 0]))


def quaternion_xyzw(R: np.ndarray) -> tuple:
    q = gtsam.Rot3(R).toQuaternion()
    xyzw = np.array([q.x(), q.y(), q.z(), q.w()])
    return tuple(float(v) for v in (xyzw if xyzw[3] >= 0 else -xyzw))


def _num(v: float) -> str:
    return f"{v:.15g}"


def load_result(result):
    """(calibration.json dict, path) of a solve output folder or the file itself."""
    path = Path(result)
    if not path.exists():
        raise InputError(path, "no such result (a folder written by solve, or its calibration.json)")
    path = path / "calibration.json" if path.is_dir() else path
    if not path.is_file():
        raise InputError(path, "missing (run 'calib3r-graph solve' first)")
    from calib3r_graph.io.results import read_calibration

    try:
        calib = read_calibration(path)
        ee_T_cam_by_camera(calib["cameras"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise InputError(path, f"not a calib3r-calibration/1 file ({type(e).__name__}: {e})") from None
    return calib, path


def _sigma_text(s: dict) -> str:
    return (f"x {s['x_mm']:.3f} y {s['y_mm']:.3f} z {s['z_mm']:.3f} mm, "
            f"rx {s['rx_deg']:.4f} ry {s['ry_deg']:.4f} rz {s['rz_deg']:.4f} deg")


def comment_lines(entry: dict, camera: str, path, convention: str) -> list:
    lines = [f"calib3r-graph hand-eye calibration of {camera}, from {path}",
             f"child: the camera's {CONVENTIONS[convention]}",
             "rpy: fixed axes X, Y, Z (R = Rz(yaw) Ry(pitch) Rx(roll)), radians; translation in metres"]
    for key in ("sigma_ee_frame", "sigma_ee_frame_model"):
        if isinstance(entry.get(key), dict):
            lines.append(f"1-sigma in the ee (parent) frame, {key}: {_sigma_text(entry[key])}")
    if len(lines) == 3:
        lines.append("no sigma in the result")
    return lines


def parent_T_child(calib: dict, camera: str | None, convention: str) -> tuple:
    cams = ee_T_cam_by_camera(calib["cameras"])
    if camera is None:
        if len(cams) != 1:
            raise InputError("--camera", f"the result has cameras {', '.join(cams)}: choose one")
        camera = next(iter(cams))
    if camera not in cams:
        raise InputError("--camera", f"no camera '{camera}' in the result (it has {', '.join(cams)})")
    T = cams[camera].matrix()
    return camera, (T @ OPTICAL_T_LINK if convention == "camera_link" else T)


def _check_frame(name: str, what: str):
    if not re.fullmatch(r"[A-Za-z0-9_/.\-]+", name or ""):
        raise InputError(what, f"'{name}' is not a frame name (letters, digits, '_', '/', '.', '-')")


def export(result, fmt: str, parent: str, child: str, camera: str | None = None, convention: str = "optical") -> str:
    if fmt not in FORMATS:
        raise InputError("--format", f"unknown format '{fmt}' (one of {', '.join(FORMATS)})")
    if convention not in CONVENTIONS:
        raise InputError("--child-convention", f"'{convention}' is not optical or camera_link")
    _check_frame(parent, "--parent")
    _check_frame(child, "--child")
    calib, path = load_result(result)
    camera, T = parent_T_child(calib, camera, convention)
    notes = comment_lines(calib["cameras"][camera], camera, path, convention)
    t = [_num(v) for v in T[:3, 3]]
    q = [_num(v) for v in quaternion_xyzw(T[:3, :3])]
    rpy = [_num(v) for v in rpy_fixed_xyz(T[:3, :3])]
    name = re.sub(r"\W", "_", child)
    xml_notes = "\n".join(f"  <!-- {n.replace('--', '- -')} -->" for n in notes)
    hash_notes = "\n".join(f"# {n}" for n in notes)
    def link_and_joint(c, p, pad):
        return "".join(f"{pad}{line}\n" for line in (
            f'<link name="{c}"/>', f'<joint name="{c}_joint" type="fixed">', f'  <parent link="{p}"/>',
            f'  <child link="{c}"/>', f'  <origin xyz="{" ".join(t)}" rpy="{" ".join(rpy)}"/>', "</joint>"))

    if fmt == "urdf":
        return (f'<?xml version="1.0"?>\n<robot name="{name}_hand_eye">\n{xml_notes}\n'
                "  <!-- paste this link and joint into your robot's URDF -->\n"
                + link_and_joint(child, parent, "  ") + "</robot>\n")
    if fmt == "xacro":
        return (f'<?xml version="1.0"?>\n<robot xmlns:xacro="http://www.ros.org/wiki/xacro">\n{xml_notes}\n'
                f'  <!-- use: <xacro:include filename="this file"/> <xacro:{name}_hand_eye/> -->\n'
                f'  <xacro:macro name="{name}_hand_eye" params="parent:={parent} child:={child}">\n'
                + link_and_joint("${child}", "${parent}", "    ") + "  </xacro:macro>\n</robot>\n")
    if fmt == "ros1-launch":
        return (f"<launch>\n{xml_notes}\n  <node pkg=\"tf2_ros\" type=\"static_transform_publisher\" "
                f"name=\"{name}_hand_eye\"\n        args=\"{' '.join(t + q)} {parent} {child}\"/>\n</launch>\n")
    if fmt == "ros2-launch":
        pad = "\n" + " " * 24
        xyz = ", ".join(f'"--{k}", "{v}"' for k, v in zip(("x", "y", "z"), t))
        quat = ", ".join(f'"--{k}", "{v}"' for k, v in zip(("qx", "qy", "qz", "qw"), q))
        return (f"{hash_notes}\n# static_transform_publisher's --x ... --child-frame-id flags: ROS 2 Humble and later\n"
                "from launch import LaunchDescription\nfrom launch_ros.actions import Node\n\n\n"
                "def generate_launch_description():\n    return LaunchDescription([\n"
                f'        Node(package="tf2_ros", executable="static_transform_publisher", name="{name}_hand_eye",\n'
                f"             arguments=[{xyz},{pad}{quat},{pad}"
                f'"--frame-id", "{parent}", "--child-frame-id", "{child}"]),\n    ])\n')
    if fmt == "tf-yaml":
        return (f"{hash_notes}\nparent_frame: {parent}\nchild_frame: {child}\nchild_convention: {convention}\n"
                f"translation: {{x: {t[0]}, y: {t[1]}, z: {t[2]}}}  # metres\n"
                f"rotation: {{x: {q[0]}, y: {q[1]}, z: {q[2]}, w: {q[3]}}}  # quaternion\n"
                f"rpy_fixed_xyz: [{', '.join(rpy)}]  # radians, as URDF\n")
    return (f"{hash_notes}\n# easy_handeye (eye on hand): transformation is robot_effector_frame -> "
            "tracking_base_frame\n"
            f"parameters:\n  namespace: /{name}_eye_on_hand/\n  eye_on_hand: true\n"
            f"  robot_effector_frame: {parent}\n  tracking_base_frame: {child}\n"
            f"transformation:\n  x: {t[0]}\n  y: {t[1]}\n  z: {t[2]}\n  qx: {q[0]}\n  qy: {q[1]}\n  qz: {q[2]}\n"
            f"  qw: {q[3]}\n")
