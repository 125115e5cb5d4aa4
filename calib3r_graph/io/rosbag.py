"""``import rosbag``: a ROS 1 ``.bag`` or a ROS 2 bag (sqlite3 or MCAP) -> calib3r-dataset/1,
through the ``rosbags`` library (no ROS install).

* ``base_T_ee`` is chained through /tf and /tf_static from ``--base-frame`` to ``--ee-frame``
  and interpolated at each image's header stamp (slerp for rotation, linear for translation).
* The first ``--image-topic`` drives the frames. An image is skipped (and the log says why)
  when /tf does not cover its stamp, when the flange moves faster than ``--max-speed-mm-s`` or
  ``--max-speed-deg-s`` within ±0.1 s of it (motion blur, camera/robot clock offsets), or when
  its flange pose is within ``--min-motion-mm`` and ``--min-motion-deg`` of the last kept
  frame (a robot resting at a pose for many images). The other cameras' images, and depth,
  are the nearest within ``--sync-tolerance-s``.
* Image and CompressedImage (JPEG and PNG are written as they are, without re-encoding);
  depth 16UC1 (mm), 32FC1 (m) and 16-bit compressedDepth, written as 16-bit PNG in mm.
* Intrinsics from each camera's CameraInfo topic (default: ``camera_info`` beside the image
  topic), or from files (``--intrinsics``).
"""

import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from calib3r_graph.errors import InputError
from calib3r_graph.io.dataset import opencv_camera, write_dataset_yaml, write_robot_poses
from calib3r_graph.io.output import atomic_path, staged_directory

log = logging.getLogger(__name__)
SPEED_WINDOW_S = 0.1  # the flange must be still within this of an image's stamp
MAX_TF_GAP_S = 0.5  # no interpolation across a longer gap in a dynamic transform
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")


@dataclass
class RosbagOptions:
    base_frame: str
    ee_frame: str
    image_topics: list
    depth_topics: list = field(default_factory=list)
    camera_info_topics: list = field(default_factory=list)
    intrinsics: list = field(default_factory=list)  # files, one per camera, instead of CameraInfo
    max_speed_mm_s: float = 10.0
    max_speed_deg_s: float = 2.0
    min_motion_mm: float = 5.0
    min_motion_deg: float = 1.0
    sync_tolerance_s: float = 0.05


def _stamp_ns(msg) -> int:
    s = msg.header.stamp
    return int(s.sec) * 1_000_000_000 + int(s.nanosec)


class TfTree:
    """Transforms from /tf and /tf_static by child frame: static ones fixed, dynamic ones as
    time series interpolated on lookup."""

    def __init__(self):
        self.parent, self.static, self.samples = {}, {}, {}

    def add(self, ts, static: bool):
        child, parent = ts.child_frame_id.lstrip("/"), ts.header.frame_id.lstrip("/")
        if self.parent.setdefault(child, parent) != parent:
            raise InputError("/tf", f"frame '{child}' has two parents, '{self.parent[child]}' and '{parent}'")
        tr, q = ts.transform.translation, ts.transform.rotation
        value = (np.array([tr.x, tr.y, tr.z]), np.array([q.x, q.y, q.z, q.w]))
        if static:
            self.static[child] = value
        else:
            self.samples.setdefault(child, []).append((_stamp_ns(ts), *value))

    def finish(self):
        self.series = {}
        for child, s in self.samples.items():
            s.sort(key=lambda x: x[0])
            stamps = np.array([x[0] for x in s], dtype=np.int64)
            keep = np.r_[True, np.diff(stamps) > 0]
            self.series[child] = (stamps[keep], np.array([x[1] for x in s])[keep],
                                  Rotation.from_quat(np.array([x[2] for x in s])[keep]))

    def chain(self, base: str, ee: str) -> list:
        """[(child frame, +1 | -1)]: the edges from base to ee (+1: along parent->child)."""
        def ancestors(f):
            out = [f]
            while out[-1] in self.parent:
                out.append(self.parent[out[-1]])
                if len(out) > 1000:
                    raise InputError("/tf", f"a loop in the tf tree above '{f}'")
            return out

        for f, flag in ((base, "--base-frame"), (ee, "--ee-frame")):
            if f not in self.parent and f not in self.parent.values():
                known = sorted(set(self.parent) | set(self.parent.values()))
                raise InputError(flag, f"frame '{f}' is not in /tf or /tf_static (frames: {', '.join(known[:12])}"
                                       f"{' ...' if len(known) > 12 else ''})")
        up_ee, up_base = ancestors(ee), ancestors(base)
        common = next((f for f in up_ee if f in up_base), None)
        if common is None:
            raise InputError("/tf", f"'{base}' and '{ee}' are not connected in the tf tree")
        down = up_ee[:up_ee.index(common)]  # ee ... below common
        up = up_base[:up_base.index(common)]  # base ... below common
        return [(f, -1) for f in up] + [(f, +1) for f in reversed(down)]

    def _edge(self, child: str, t_ns: int):
        if child in self.series:
            stamps, trans, rots = self.series[child]
            if t_ns < stamps[0] or t_ns > stamps[-1]:
                return None
            i = int(np.searchsorted(stamps, t_ns))
            if stamps[i] == t_ns or len(stamps) == 1:
                return trans[i], rots[i].as_matrix()
            if (stamps[i] - stamps[i - 1]) * 1e-9 > MAX_TF_GAP_S:
                return None
            a = (t_ns - stamps[i - 1]) / (stamps[i] - stamps[i - 1])
            rel = (rots[i - 1].inv() * rots[i]).as_rotvec()
            R = (rots[i - 1] * Rotation.from_rotvec(a * rel)).as_matrix()  # slerp
            return (1 - a) * trans[i - 1] + a * trans[i], R
        t, q = self.static[child]
        return t, Rotation.from_quat(q).as_matrix()

    def lookup(self, chain: list, t_ns: int):
        """base_T_ee (4x4) at a stamp, or None where a dynamic transform does not cover it."""
        T = np.eye(4)
        for child, sign in chain:
            e = self._edge(child, t_ns)
            if e is None:
                return None
            E = np.eye(4)
            E[:3, :3], E[:3, 3] = e[1], e[0]
            T = T @ (E if sign > 0 else np.linalg.inv(E))
        return T


def _motion(A, B) -> tuple:
    """(mm, deg) between two poses."""
    dR = A[:3, :3].T @ B[:3, :3]
    ang = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(A[:3, 3] - B[:3, 3]) * 1e3), float(ang)


def _open(bag: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if not bag.exists():
        raise InputError(bag, "no such bag")
    if bag.is_file() and bag.suffix.lower() in (".db3", ".mcap") and (bag.parent / "metadata.yaml").is_file():
        bag = bag.parent  # a ROS 2 bag is its folder
    try:
        reader = AnyReader([bag], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except Exception as e:  # rosbags raises its own error classes for every kind of unreadable bag
        raise InputError(bag, f"not a readable ROS 1 or ROS 2 bag ({type(e).__name__}: {e})") from None
    return reader


def _connections(reader, topic: str, types, flag: str) -> list:
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        avail = sorted({c.topic for c in reader.connections if c.msgtype in types})
        raise InputError(flag, f"no topic '{topic}' in the bag (topics of that kind: {', '.join(avail) or 'none'})")
    bad = [c.msgtype for c in conns if c.msgtype not in types]
    if bad:
        raise InputError(flag, f"topic '{topic}' has type {bad[0]}, expected {' or '.join(types)}")
    return conns


def decode_image(msg, depth: bool):
    """(array, encoded bytes to write as they are or None, suffix). Depth: uint16 mm."""
    if hasattr(msg, "encoding"):  # sensor_msgs/Image
        enc, h, w = msg.encoding.lower(), int(msg.height), int(msg.width)
        raw = np.frombuffer(bytes(msg.data), np.uint8).reshape(h, int(msg.step))
        kinds = {"rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4),
                 "mono8": (np.uint8, 1), "8uc1": (np.uint8, 1), "8uc3": (np.uint8, 3), "mono16": (np.uint16, 1),
                 "16uc1": (np.uint16, 1), "32fc1": (np.float32, 1)}
        if enc not in kinds:
            raise ValueError(f"image encoding '{msg.encoding}' is not supported")
        dt, ch = kinds[enc]
        item = np.dtype(dt).itemsize
        arr = raw[:, :w * ch * item].copy().view(np.dtype(dt).newbyteorder(">" if msg.is_bigendian else "<"))
        arr = arr.astype(dt).reshape(h, w, ch) if ch > 1 else arr.astype(dt).reshape(h, w)
        if depth:
            if enc == "32fc1":
                arr = np.where(np.isfinite(arr) & (arr > 0), np.round(arr * 1000.0), 0).clip(0, 65535)
            elif enc not in ("16uc1", "mono16"):
                raise ValueError(f"depth encoding '{msg.encoding}' is not supported (16UC1 mm or 32FC1 m)")
            return arr.astype(np.uint16), None, ".png"
        if enc in ("rgb8", "rgba8"):
            arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR if ch == 3 else cv2.COLOR_RGBA2BGR)
        elif enc == "bgra8":
            arr = cv2.cvtColor(arr, cv2.COLOR_BGRA2BGR)
        return arr, None, ".png"
    data, fmt = bytes(msg.data), msg.format.lower()
    if "compresseddepth" in fmt:  # 12-byte header (format and quantisation), then a 16-bit PNG
        if "32fc1" in fmt:
            raise ValueError("32FC1 compressedDepth (quantised inverse depth) is not supported")
        data = data[12:]
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise ValueError(f"CompressedImage ({msg.format}) does not decode")
    if depth:
        if arr.dtype != np.uint16:
            raise ValueError("compressed depth is not 16-bit")
        return arr, None, ".png"
    suffix = ".jpg" if data[:2] == b"\xff\xd8" else ".png" if data[:4] == b"\x89PNG" else None
    return arr, (data if suffix else None), suffix or ".png"


def _default_info_topic(image_topic: str) -> str:
    t = image_topic[:-len("/compressed")] if image_topic.endswith("/compressed") else image_topic
    return t.rsplit("/", 1)[0] + "/camera_info"


def _camera_info(msg, topic: str, size):
    from calib3r_graph.io.intrinsics_files import opencv_distortion

    K = np.asarray(getattr(msg, "k", None) if hasattr(msg, "k") else msg.K, dtype=float).reshape(3, 3)
    D = getattr(msg, "d", None) if hasattr(msg, "d") else msg.D
    if not K[0, 0] > 0:
        raise InputError(topic, "CameraInfo has no intrinsics (K is zero): the camera is not calibrated")
    if (int(msg.width), int(msg.height)) != tuple(size):
        raise InputError(topic, f"CameraInfo is for {msg.width}x{msg.height} images but the images are "
                                f"{size[0]}x{size[1]}")
    return K, opencv_distortion(D, msg.distortion_model, topic)


def _nearest(stamps: np.ndarray, t: int, tol_s: float):
    if len(stamps) == 0:
        return None
    i = int(np.argmin(np.abs(stamps - t)))
    return i if abs(int(stamps[i]) - t) * 1e-9 <= tol_s else None


def import_rosbag(bag, dst, opt: RosbagOptions) -> str:
    bag, dst = Path(bag), Path(dst)
    n_cams = len(opt.image_topics)
    if len(opt.depth_topics) > n_cams or len(opt.camera_info_topics) > n_cams:
        raise InputError("--depth-topic", "more depth or camera_info topics than image topics (one per camera)")
    reader = _open(bag)
    try:
        return _import(reader, bag, dst, opt, n_cams)
    finally:
        reader.close()


def _read_pass1(reader, opt, n_cams):
    """The tf tree, each camera's image and depth stamps, and its first CameraInfo."""
    img_conns = [_connections(reader, t, IMAGE_TYPES, "--image-topic") for t in opt.image_topics]
    depth_conns = [_connections(reader, t, IMAGE_TYPES, "--depth-topic") for t in opt.depth_topics]
    info_topics = list(opt.camera_info_topics)
    if not opt.intrinsics:
        for j in range(len(info_topics), n_cams):
            info_topics.append(_default_info_topic(opt.image_topics[j]))
        info_conns = [_connections(reader, t, ("sensor_msgs/msg/CameraInfo",), "--camera-info-topic")
                      for t in info_topics]
    else:
        info_conns = []
    tf_conns = [c for c in reader.connections if c.topic in ("/tf", "/tf_static", "tf", "tf_static")]
    if not tf_conns:
        raise InputError("/tf", "the bag has no /tf or /tf_static topic: the flange poses come from them")
    tree = TfTree()
    stamps = {("img", j): [] for j in range(n_cams)} | {("depth", j): [] for j in range(len(depth_conns))}
    infos = {}
    topic_of = {}
    for j, cs in enumerate(img_conns):
        topic_of.update({c.id: ("img", j) for c in cs})
    for j, cs in enumerate(depth_conns):
        topic_of.update({c.id: ("depth", j) for c in cs})
    info_of = {c.id: j for j, cs in enumerate(info_conns) for c in cs}
    conns = tf_conns + [c for cs in img_conns + depth_conns + info_conns for c in cs]
    for conn, t_bag, raw in reader.messages(connections=conns):
        msg = reader.deserialize(raw, conn.msgtype)
        if conn in tf_conns:
            for ts in msg.transforms:
                tree.add(ts, static="static" in conn.topic)
        elif conn.id in info_of:
            infos.setdefault(info_of[conn.id], msg)
        else:
            stamps[topic_of[conn.id]].append(_stamp_ns(msg))
    tree.finish()
    return tree, {k: np.array(v, dtype=np.int64) for k, v in stamps.items()}, infos, info_topics


def _select(tree, chain, stamps, opt, n_cams, n_depth):
    """The frames to keep: [(cam0 image index, base_T_ee, {cam: image index}, {cam: depth index})], skip counts."""
    skipped = {"no tf": [], "moving": [], "too close": [], "no partner image": []}
    kept, last = [], None
    w = int(max(SPEED_WINDOW_S, opt.sync_tolerance_s) * 1e9)
    order = np.argsort(stamps[("img", 0)], kind="stable")
    for i in order:
        t = int(stamps[("img", 0)][i])
        T, Ta, Tb = tree.lookup(chain, t), tree.lookup(chain, t - w), tree.lookup(chain, t + w)
        if T is None or Ta is None or Tb is None:
            skipped["no tf"].append(t)
            continue
        mm, deg = _motion(Ta, Tb)
        speed = (mm / (2 * w * 1e-9), deg / (2 * w * 1e-9))
        if speed[0] > opt.max_speed_mm_s or speed[1] > opt.max_speed_deg_s:
            skipped["moving"].append(t)
            log.debug("image at %.3f s skipped: the flange moves %.1f mm/s, %.2f deg/s", t * 1e-9, *speed)
            continue
        if last is not None:
            mm, deg = _motion(last, T)
            if mm < opt.min_motion_mm and deg < opt.min_motion_deg:
                skipped["too close"].append(t)
                continue
        others = {j: _nearest(stamps[("img", j)], t, opt.sync_tolerance_s) for j in range(1, n_cams)}
        if any(v is None for v in others.values()):
            skipped["no partner image"].append(t)
            continue
        imgs = {0: int(i), **others}
        depth = {}
        for j in range(n_depth):
            k = _nearest(stamps[("depth", j)], int(stamps[("img", j)][imgs[j]]), opt.sync_tolerance_s)
            if k is not None:
                depth[j] = k
        kept.append((t, T, imgs, depth))
        last = T
    return kept, skipped


def _import(reader, bag, dst, opt, n_cams) -> str:
    tree, stamps, infos, info_topics = _read_pass1(reader, opt, n_cams)
    chain = tree.chain(opt.base_frame.lstrip("/"), opt.ee_frame.lstrip("/"))
    n_depth = len(opt.depth_topics)
    if len(stamps[("img", 0)]) == 0:
        raise InputError(opt.image_topics[0], "no messages on this topic")
    kept, skipped = _select(tree, chain, stamps, opt, n_cams, n_depth)
    if len(kept) < 3:
        raise InputError(bag, f"only {len(kept)} of {len(stamps[('img', 0)])} images kept (skipped: "
                              + ", ".join(f"{len(v)} {k}" for k, v in skipped.items() if v)
                              + "): check the frames, --max-speed-mm-s/--max-speed-deg-s and --min-motion-mm/-deg")
    frames = [f"{k:04d}" for k in range(len(kept))]
    want = {}  # (kind, cam, index within topic) -> frame
    for f, (_, _, imgs, depth) in zip(frames, kept):
        want.update({("img", j, i): f for j, i in imgs.items()})
        want.update({("depth", j, i): f for j, i in depth.items()})
    sizes, counters = {}, {}
    with staged_directory(dst) as stage:
        conns = [c for t in opt.image_topics + opt.depth_topics for c in reader.connections if c.topic == t]
        kind_of = {c.id: ("img", j) for j, t in enumerate(opt.image_topics) for c in reader.connections if c.topic == t}
        kind_of.update({c.id: ("depth", j) for j, t in enumerate(opt.depth_topics)
                        for c in reader.connections if c.topic == t})
        for conn, _, raw in reader.messages(connections=conns):
            kind, j = kind_of[conn.id]
            # Indices count messages per topic in bag order, as in the first pass; the
            # stamps were sorted for selection only, so the index identifies the message.
            idx = counters.get((kind, j), 0)
            counters[(kind, j)] = idx + 1
            frame = want.get((kind, j, idx))
            if frame is None:
                continue
            msg = reader.deserialize(raw, conn.msgtype)
            try:
                arr, data, suffix = decode_image(msg, depth=kind == "depth")
            except ValueError as e:
                raise InputError(conn.topic, str(e)) from None
            folder = stage / ("images" if kind == "img" else "depth") / f"cam{j}"
            folder.mkdir(parents=True, exist_ok=True)
            with atomic_path(folder / f"{frame}{suffix}") as tmp:
                if data is not None:
                    tmp.write_bytes(data)
                elif not cv2.imwrite(str(tmp), arr):
                    raise OSError(f"cannot encode {folder / frame}{suffix}")
            size = (arr.shape[1], arr.shape[0])
            if sizes.setdefault((kind, j), size) != size:
                raise InputError(conn.topic, f"image sizes change within the topic ({sizes[(kind, j)]} then {size})")
        cams = _cameras(opt, infos, info_topics, sizes, n_cams)
        base_T_ee = {f: _pose3(T) for f, (_, T, _, _) in zip(frames, kept)}
        write_robot_poses(stage / "robot_poses.csv", base_T_ee, unit="m")
        write_dataset_yaml(stage, cams, unit="m", extra={"source": {
            "format": "rosbag", "path": str(bag), "base_frame": opt.base_frame, "ee_frame": opt.ee_frame,
            "image_topics": list(opt.image_topics), "depth_topics": list(opt.depth_topics),
            "intrinsics": list(map(str, opt.intrinsics)) or info_topics,
            "stamps_ns": {f: int(t) for f, (t, _, _, _) in zip(frames, kept)}}})
    lines = [f"imported {len(kept)} frames x {n_cams} camera(s) of {bag} into {dst}",
             f"  base_T_ee: {opt.base_frame} -> {opt.ee_frame} through "
             f"{' -> '.join(c for c, _ in chain) or '(the same frame)'}, interpolated at each image stamp",
             f"  {len(stamps[('img', 0)])} images on {opt.image_topics[0]}: kept {len(kept)}"]
    reasons = {"no tf": "outside /tf's time span", "moving": f"flange faster than {opt.max_speed_mm_s:g} mm/s or "
               f"{opt.max_speed_deg_s:g} deg/s", "too close": f"within {opt.min_motion_mm:g} mm and "
               f"{opt.min_motion_deg:g} deg of the last kept frame", "no partner image": "another camera has no "
               f"image within {opt.sync_tolerance_s:g} s"}
    t_first = int(stamps[("img", 0)].min())
    for k, v in skipped.items():
        if v:
            msg = (f"skipped {len(v)} images: {reasons[k]} (the first {(v[0] - t_first) * 1e-9:.3f} s after the "
                   "first image)")
            log.info(msg)
            lines.append(f"  {msg}")
    for j in range(n_depth):
        got = sum(1 for _, _, _, d in kept if j in d)
        lines.append(f"  depth cam{j}: {got} of {len(kept)} frames from {opt.depth_topics[j]}")
    return "\n".join(lines)


def _pose3(T):
    import gtsam

    return gtsam.Pose3(gtsam.Rot3(T[:3, :3]), T[:3, 3])


def _cameras(opt, infos, info_topics, sizes, n_cams) -> list:
    from calib3r_graph.io.intrinsics_files import read_intrinsics

    files = [i for f in opt.intrinsics for i in read_intrinsics(f)]
    if opt.intrinsics and len(files) != n_cams:
        raise InputError("--intrinsics", f"{len(files)} camera(s) in the intrinsics file(s) for {n_cams} image topics")
    cams = []
    for j in range(n_cams):
        size = sizes[("img", j)]
        if files:
            K, dist = files[j].K, files[j].dist
            if files[j].width is not None and (files[j].width, files[j].height) != size:
                raise InputError(files[j].source, f"intrinsics for {files[j].width}x{files[j].height} images but the "
                                                  f"images are {size[0]}x{size[1]}")
        else:
            if j not in infos:
                raise InputError(info_topics[j], "no CameraInfo message on this topic")
            K, dist = _camera_info(infos[j], info_topics[j], size)
        depth_scale = 0.001 if ("depth", j) in sizes else None
        if depth_scale and sizes[("depth", j)] != size:
            raise InputError(opt.depth_topics[j], f"depth is {sizes[('depth', j)][0]}x{sizes[('depth', j)][1]} but "
                                                  f"the images are {size[0]}x{size[1]}: it must be registered to "
                                                  "the colour camera")
        cams.append(opencv_camera(f"cam{j}", size, K, dist, depth_scale))
    return cams
