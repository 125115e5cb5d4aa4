"""``import rosbag``: the simulator's recording played as a robot would publish it (the flange
resting at each pose, then moving to the next; /tf through two moving joints and a static
flange offset; images and depth streaming throughout), written with rosbags' own writers as a
ROS 1 .bag and as ROS 2 MCAP and sqlite3 bags. The import keeps exactly one image per rest,
reproduces the original dataset bit for bit, and solves to the simulator's truth."""

import json
import shutil

import cv2
import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from calib3r_graph.cli import main
from calib3r_graph.errors import InputError
from calib3r_graph.evaluation.evaluate import evaluate
from calib3r_graph.io.dataset import load_dataset, load_ground_truth
from calib3r_graph.io.rosbag import TfTree

T0 = 1_700_000_000 * 10**9  # a realistic epoch, ns
REST_S, MOVE_S = 1.0, 1.0  # the flange rests at each pose, then moves to the next
TF_HZ, IMAGE_PERIOD_S = 50.0, 0.4
TOOL0_T_FLANGE = gtsam.Pose3(gtsam.Rot3.Rz(np.pi / 4), np.array([0.0, 0.0, 0.012]))


@pytest.fixture(scope="module")
def sims(tmp_path_factory):
    from calib3r_graph.simulate import SimOptions, simulate

    root = tmp_path_factory.mktemp("sim")
    small = dict(images=True, width=320, height=240, matches_per_pair=400)
    return {"one": simulate(root / "one", SimOptions(seed=21, frames=8, cameras=1, **small), progress=False),
            "rig": simulate(root / "rig", SimOptions(seed=22, frames=4, cameras=2, **small), progress=False)}


def flange_at(poses, t_s):
    """base_T_flange at a time of the recording (resting, or moving with slerp), and whether it rests."""
    k = int(t_s // (REST_S + MOVE_S))
    u = t_s - k * (REST_S + MOVE_S)
    if u <= REST_S or k + 1 >= len(poses):
        return poses[min(k, len(poses) - 1)], True
    a = (u - REST_S) / MOVE_S
    A, B = poses[k], poses[k + 1]
    rot = Slerp([0, 1], Rotation.from_matrix([A[:3, :3], B[:3, :3]]))([a]).as_matrix()[0]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rot, (1 - a) * A[:3, 3] + a * B[:3, 3]
    return T, False


def tf_msgs(ts, poses, t_s, ros1):
    """The TransformStamped list of /tf at a time: base_link -> link_1 (a yaw joint) -> tool0."""
    E, _ = flange_at(poses, t_s)
    base_T_tool0 = E @ np.linalg.inv(TOOL0_T_FLANGE.matrix())
    yaw = np.arctan2(base_T_tool0[1, 3], base_T_tool0[0, 3])
    base_T_link1 = gtsam.Pose3(gtsam.Rot3.Rz(yaw), np.array([0.0, 0.0, 0.3])).matrix()
    link1_T_tool0 = np.linalg.inv(base_T_link1) @ base_T_tool0
    stamp = T0 + int(round(t_s * 1e9))
    return [transform(ts, "base_link", "link_1", base_T_link1, stamp, ros1),
            transform(ts, "link_1", "tool0", link1_T_tool0, stamp, ros1)]


def header(ts, stamp, frame, ros1):
    Time, Header = ts.types["builtin_interfaces/msg/Time"], ts.types["std_msgs/msg/Header"]
    t = Time(sec=stamp // 10**9, nanosec=stamp % 10**9)
    return Header(seq=0, stamp=t, frame_id=frame) if ros1 else Header(stamp=t, frame_id=frame)


def transform(ts, parent, child, T, stamp, ros1):
    g = "geometry_msgs/msg/"
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    tr = ts.types[g + "Transform"](translation=ts.types[g + "Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                                   rotation=ts.types[g + "Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
    return ts.types[g + "TransformStamped"](header=header(ts, stamp, parent, ros1), child_frame_id=child, transform=tr)


def image_msg(ts, img, stamp, ros1, compressed, depth=False):
    h = header(ts, stamp, "cam", ros1)
    if compressed:
        data = cv2.imencode(".png", img)[1].ravel()
        return "sensor_msgs/msg/CompressedImage", ts.types["sensor_msgs/msg/CompressedImage"](
            header=h, format="16UC1; compressedDepth png" if depth else "png",
            data=np.r_[np.zeros(12, np.uint8), data] if depth else data)
    if depth and not ros1:  # ROS 2 depth as 32FC1 metres
        arr, enc = (img.astype(np.float32) / 1000.0), "32FC1"
        arr[img == 0] = np.nan
    elif depth:
        arr, enc = img, "16UC1"
    else:
        arr, enc = cv2.cvtColor(img, cv2.COLOR_BGR2RGB), "rgb8"
    raw = np.ascontiguousarray(arr).view(np.uint8)
    return "sensor_msgs/msg/Image", ts.types["sensor_msgs/msg/Image"](
        header=h, height=arr.shape[0], width=arr.shape[1], encoding=enc, is_bigendian=0,
        step=raw.nbytes // arr.shape[0], data=raw.ravel())


def camera_info(ts, cam, stamp, ros1):
    K, D = cam.K.ravel().astype(float), np.zeros(5)
    R, P = np.eye(3).ravel(), np.c_[cam.K, np.zeros(3)].ravel()
    roi = ts.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    fields = dict(header=header(ts, stamp, "cam", ros1), height=cam.height, width=cam.width,
                  distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi)
    fields.update(dict(D=D, K=K, R=R, P=P) if ros1 else dict(d=D, k=K, r=R, p=P))
    return ts.types["sensor_msgs/msg/CameraInfo"](**fields)


def write_bag(sim, path, kind):
    """Play the simulator's recording into a bag: kind ros1 (raw images, 16UC1 depth) or
    mcap/sqlite3 (PNG CompressedImage, 32FC1 depth for cam0, compressedDepth for cam1)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ros1 = kind == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in ts.types:
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    ds = load_dataset(sim)
    poses = [ds.base_T_ee[f].compose(gtsam.Pose3()).matrix() for f in ds.frames]
    if ros1:
        from rosbags.rosbag1 import Writer

        writer, ser = Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer, ser = Writer(path, version=9, storage_plugin=plugin), ts.serialize_cdr
    conns = {}

    def put(topic, msgtype, msg, stamp):
        if topic not in conns:
            conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
        writer.write(conns[topic], stamp + 3_000_000, ser(msg, msgtype))  # received 3 ms after the stamp

    duration = len(poses) * (REST_S + MOVE_S) - MOVE_S
    with writer:
        E0 = TOOL0_T_FLANGE.matrix()
        put("/tf_static", "tf2_msgs/msg/TFMessage", ts.types["tf2_msgs/msg/TFMessage"](transforms=[
            transform(ts, "tool0", "flange", E0, T0, ros1),
            transform(ts, "world", "base_link", np.eye(4), T0, ros1),
            transform(ts, "flange", "cam0_mount", np.eye(4), T0, ros1)]), T0)
        events = [(k / TF_HZ - 0.007, "tf") for k in range(int((duration + 0.2) * TF_HZ))]
        events += [(0.1 + k * IMAGE_PERIOD_S, "img") for k in range(int(duration / IMAGE_PERIOD_S))]
        for t_s, what in sorted(events):
            stamp = T0 + int(round(t_s * 1e9))
            if what == "tf":
                put("/tf", "tf2_msgs/msg/TFMessage", ts.types["tf2_msgs/msg/TFMessage"](
                    transforms=tf_msgs(ts, poses, max(t_s, 0.0), ros1)), stamp)
                continue
            frame = ds.frames[min(int(t_s // (REST_S + MOVE_S)), len(poses) - 1)]  # moving: the last image
            for j, cam in enumerate(ds.cameras.values()):
                img = cv2.imread(str(ds.image_path(cam.name, frame)), cv2.IMREAD_COLOR)
                depth = cv2.imread(str(ds.depth_path(cam.name, frame)), cv2.IMREAD_UNCHANGED)
                s = stamp + 2_000_000 * j  # the rig's cameras fire 2 ms apart
                put(f"/{cam.name}/color/image_raw", *image_msg(ts, img, s, ros1, compressed=not ros1), s)
                put(f"/{cam.name}/depth/image_rect", *image_msg(ts, depth, s, ros1, compressed=(j == 1 and not ros1),
                                                                  depth=True), s)
                put(f"/{cam.name}/color/camera_info", "sensor_msgs/msg/CameraInfo", camera_info(ts, cam, s, ros1), s)
    return path


def assert_same_dataset(imported, original):
    a, b = load_dataset(imported), load_dataset(original)
    assert a.frames == b.frames
    for f in a.frames:
        np.testing.assert_allclose(a.base_T_ee[f].matrix(), b.base_T_ee[f].matrix(), atol=1e-9)
    for name, cam in b.cameras.items():
        np.testing.assert_allclose(a.cameras[name].K, cam.K, rtol=1e-12)
        assert a.cameras[name].dist.tolist() == [0.0] * 4 and a.cameras[name].depth_scale == 0.001
        for f in a.frames:
            for kind, read in (("image", cv2.IMREAD_COLOR), ("depth", cv2.IMREAD_UNCHANGED)):
                path = (a.image_path if kind == "image" else a.depth_path)(name, f)
                ref = (b.image_path if kind == "image" else b.depth_path)(name, f)
                assert np.array_equal(cv2.imread(str(path), read), cv2.imread(str(ref), read)), (kind, name, f)


def args(bag, dst, cams, depth=True):
    out = ["import", "rosbag", str(bag), str(dst), "--base-frame", "base_link", "--ee-frame", "flange"]
    for c in cams:
        out += ["--image-topic", f"/{c}/color/image_raw"] + (["--depth-topic", f"/{c}/depth/image_rect"]
                                                             if depth else [])
    return out


@pytest.mark.slow
def test_ros1_bag_imports_and_solves_to_the_truth(sims, tmp_path, capsys):
    bag = write_bag(sims["one"], tmp_path / "rec.bag", "ros1")
    dst = tmp_path / "ds"
    assert main(args(bag, dst, ["cam0"])) == 0
    out = capsys.readouterr().out
    assert "imported 8 frames x 1 camera(s)" in out
    assert "base_link -> flange through link_1 -> tool0 -> flange" in out
    assert "flange faster than 10 mm/s" in out and "within 5 mm and 1 deg of the last kept frame" in out
    assert_same_dataset(dst, sims["one"])
    # Solve with the simulator's predictions for these views: as accurate as the original.
    shutil.copytree(sims["one"] / "predictions", dst / "predictions")
    shutil.copyfile(sims["one"] / "ground_truth.yaml", dst / "ground_truth.yaml")
    assert main(["-q", "solve", str(dst), "--out", str(tmp_path / "res"), "--no-cloud",
                 "--max-matches-per-pair", "300"]) == 0
    err = evaluate(tmp_path / "res", dst)["hand_eye"]["cam0"]
    assert err["e_t_m"] < 2e-3 and np.degrees(err["e_theta_rad"]) < 0.15, err
    # The imported bag replays through live frame by frame, and its last update is solve's result.
    assert main(["-q", "live", str(dst), "--replay", "recorded", "--out", str(tmp_path / "live")]) == 0
    steps = [json.loads(line) for line in (tmp_path / "live" / "live.jsonl").read_text().splitlines()]
    assert [s["frames"][-1] for s in steps[:8]] == load_dataset(dst).frames
    T_live = np.array(json.loads((tmp_path / "live" / "calibration.json").read_text())["cameras"]["cam0"]["T_ee_cam"])
    T_gt = load_ground_truth(dst)["hand_eye"]["cam0"].matrix()
    assert np.linalg.norm(T_live[:3, 3] - T_gt[:3, 3]) < 2e-3


@pytest.mark.slow
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_ros2_bags_of_a_rig(sims, tmp_path, capsys, storage):
    bag = write_bag(sims["rig"], tmp_path / "rec", storage)
    dst = tmp_path / "ds"
    assert main(args(bag, dst, ["cam0", "cam1"])) == 0
    assert "imported 4 frames x 2 camera(s)" in capsys.readouterr().out
    assert_same_dataset(dst, sims["rig"])
    # Too strict a still-bound keeps nothing: one clear line.
    assert main(args(bag, tmp_path / "none", ["cam0"], depth=False) + ["--min-motion-mm", "5000",
                                                                        "--min-motion-deg", "500"]) == 3
    err = capsys.readouterr().err
    assert "only 1 of" in err and err.count("\n") == 1


def test_tf_interpolation_and_chains():
    """Slerp of a constant-rate rotation is exact between samples; a chain climbs up and down the tree."""
    from types import SimpleNamespace as NS

    def ts(parent, child, t_s, T):
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        stamp = NS(sec=int(t_s), nanosec=int(round((t_s % 1) * 1e9)))
        return NS(header=NS(frame_id=parent, stamp=stamp), child_frame_id=child,
                  transform=NS(translation=NS(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                               rotation=NS(x=q[0], y=q[1], z=q[2], w=q[3])))

    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])

    def world_T_a(t):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Rotation.from_rotvec(axis * 0.8 * t).as_matrix(), [0.1 * t, -0.2 * t, 0.5]
        return T

    world_T_b = gtsam.Pose3(gtsam.Rot3.Ry(0.4), np.array([1.0, 0.0, 0.0])).matrix()
    tree = TfTree()
    for k in range(11):
        tree.add(ts("world", "a", 100 + 0.1 * k, world_T_a(0.1 * k)), static=False)
    tree.add(ts("world", "b", 0, world_T_b), static=True)
    tree.finish()
    chain = tree.chain("b", "a")
    assert chain == [("b", -1), ("a", +1)]
    for t in (0.0, 0.137, 0.55, 0.999):
        T = tree.lookup(chain, int((100 + t) * 1e9))
        np.testing.assert_allclose(T, np.linalg.inv(world_T_b) @ world_T_a(t), atol=1e-9)
    assert tree.lookup(chain, int(101.01e9)) is None  # after the last sample
    with pytest.raises(InputError, match="'nowhere' is not in /tf"):
        tree.chain("nowhere", "a")
