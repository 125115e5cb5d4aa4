"""``LiveSession``: the Python API of a live, guided calibration, and what ``calib3r-graph live`` runs.

    from calib3r_graph.live import LiveSession
    session = LiveSession("my_dataset", target_mm=1.0, target_deg=0.1, out="live_out")
    for frame_id, base_T_ee, image in capture():              # your robot / ROS loop
        up = session.add_frame(frame_id, base_T_ee, images={"cam0": image})   # path or HxWx3 uint8
        print(up.status_line())
        if up.done:
            break
        robot.move_to(up.next_poses[0])                       # 4x4 base_T_ee, the best first

After each update ``out`` holds ``calibration.json`` (the current calibration, as ``solve``
writes it), ``next_poses.csv`` (in the dataset's robot pose format and unit, or with
``next_pose_format`` in another: the pose file ``--watch --poses`` reads) and one more line of
``live.jsonl``, each written atomically. A frame whose image cannot be read, or whose pose is
missing or not finite, is named in the update (``skipped``) and left out; the session goes on.
"""

import dataclasses
import json
import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import gtsam
import numpy as np

from calib3r_graph.errors import Calib3rError, InputError
from calib3r_graph.io.dataset import Dataset, load_dataset
from calib3r_graph.io.output import atomic_write_json, atomic_write_text
from calib3r_graph.io.results import (calibration_json, covariance_in_ee_frame, largest_sigma, sigma_ee_frame,
                                      uncertainty_report)
from calib3r_graph.live.engine import Engine
from calib3r_graph.live.poses import open_tail, read_pose_rows, read_text
from calib3r_graph.solver.solve import SolveOptions
from calib3r_graph.solver.uncertainty import MIN_CHECKED_POSES

log = logging.getLogger(__name__)

K_NEXT = 5


@dataclass
class Update:
    step: int
    frames: list
    latency_s: float  # the solver's update (placement, LM, covariance, guidance), without the frontend
    frontend_s: dict  # the new frame's feature extraction and pair geometry, aggregation
    guidance_s: float = 0.0  # of latency_s: proposing and scoring the next poses
    cpu_s: float = 0.0  # the CPU time of latency_s (time.process_time: a loaded machine stretches the wall time)
    frontend_cpu_s: float = 0.0  # the CPU time of the frontend's part (frontend_s), features included
    ee_T_cam: dict = field(default_factory=dict)  # camera -> 4x4
    sigma_ee_frame: dict = field(default_factory=dict)  # camera -> total sigma per ee axis (deg, mm)
    metric_scale: dict = field(default_factory=dict)  # camera -> (value, sigma)
    next_poses: list = field(default_factory=list)  # 4x4 base_T_ee, best first
    next_kinds: list = field(default_factory=list)
    done: bool = False
    floor: bool = False  # the systematic floor alone is above the target: more poses will not help
    # the total sigma is checked by a leave-one-pose-out (uncertainty.MIN_CHECKED_POSES poses or more);
    # below, it is the model's, often too small on real arms, and the session is never "done"
    sigma_checked: bool = False
    message: str = ""
    skipped: list = field(default_factory=list)  # (frame, reason)
    calibration: dict | None = field(default=None, repr=False)

    def largest(self) -> tuple[float, float]:
        """Largest total sigma over cameras and axes: (mm, deg); inf before the first solve."""
        if not self.sigma_ee_frame:
            return float("inf"), float("inf")
        return largest_sigma(self.sigma_ee_frame)

    def status_line(self) -> str:
        mm, deg = self.largest()
        nxt = ""
        if self.next_poses:
            T = np.asarray(self.next_poses[0])
            nxt = (f"  next ({self.next_kinds[0]}): xyz {T[0, 3]:.3f} {T[1, 3]:.3f} {T[2, 3]:.3f} m")
        sig = f"sigma {mm:.2f} mm {deg:.3f} deg" if np.isfinite(mm) else "sigma -"
        if np.isfinite(mm) and not self.sigma_checked:
            sig += " (unchecked)"
        state = "DONE" if self.done else ("FLOOR" if self.floor else "")
        skipped = "".join(f"  skipped {f}: {r}" for f, r in self.skipped)
        # the time the frame took to answer: its features and pairs, then the solver's update
        wait = f"{self.latency_s + sum(self.frontend_s.values()):.2f} s (solver {self.latency_s:.2f} s)"
        return (f"[{self.step:3d}] frames {len(self.frames):3d}  {sig}  {wait}"
                f"{nxt}  {state} {self.message}{skipped}").rstrip()

    def to_json(self) -> dict:
        return {"step": self.step, "frames": self.frames, "latency_s": self.latency_s, "cpu_s": self.cpu_s,
                "frontend_s": self.frontend_s, "frontend_cpu_s": self.frontend_cpu_s,
                "guidance_s": self.guidance_s,
                "cameras": {c: {"T_ee_cam": self.ee_T_cam[c], "sigma_ee_frame": self.sigma_ee_frame[c],
                                "metric_scale": self.metric_scale[c][0], "metric_scale_sigma": self.metric_scale[c][1]}
                            for c in self.ee_T_cam},
                "next_poses": self.next_poses, "next_kinds": self.next_kinds, "done": self.done,
                "floor": self.floor, "sigma_checked": self.sigma_checked, "message": self.message,
                "skipped": [list(s) for s in self.skipped]}


def session_dataset(dataset_dir, name_bad_rows: bool = False) -> Dataset:
    """The dataset's cameras, intrinsics and robot unit, and its robot poses: frames are added as
    they arrive, so a missing or header-only pose file is fine, and a row that does not parse
    (a capture script's NaN) leaves out that frame only (:func:`read_pose_rows` names it; with
    ``name_bad_rows`` a warning says so, once: a replay never adds that frame)."""
    root = Path(dataset_dir)
    quiet = logging.getLogger("calib3r_graph.io")  # images waiting for their pose row are expected here
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        return load_dataset(root, skip_missing=True)
    except InputError as e:
        import tempfile

        import yaml

        meta_path = root / "dataset.yaml"
        if not meta_path.is_file():
            raise
        meta = yaml.safe_load(meta_path.read_text())
        robot = (meta.get("robot") or {}) if isinstance(meta, dict) else {}
        poses = robot.get("poses", "robot_poses.csv")
        if e.path != str(root / poses):  # dataset.yaml itself, not the poses being written
            raise
        with tempfile.TemporaryDirectory() as tmp:  # the cameras alone: a placeholder pose beside a copy
            shutil.copy(meta_path, Path(tmp) / "dataset.yaml")
            (Path(tmp) / poses).write_text("frame,x,y,z,qx,qy,qz,qw\nplaceholder,0,0,0,0,0,0,1\n")
            ds = load_dataset(tmp)
        text = read_text(root / poses)[0] or ""
        rows = read_pose_rows(root / poses, ds.robot_unit, text)
        for i, (_, T, why) in enumerate(rows):
            if T is None and name_bad_rows:
                if i == len(rows) - 1 and open_tail(text):  # it may be being written
                    log.warning("%s (the file's last line, without its line end: a replay leaves that frame out, "
                                "--watch reads it once whole)", why)
                else:
                    log.warning("%s; that frame is left out", why)
        good = {f: gtsam.Pose3(T) for f, T, _ in rows if T is not None}
        return dataclasses.replace(ds, root=root, base_T_ee=good)
    finally:
        quiet.setLevel(level)


class LiveSession:
    """A live calibration over frames added one at a time (see the module's docstring).

    ``predictions``: use the dataset's ``predictions/<name>/`` for the frames (a recording replayed);
    otherwise the pairwise frontend runs on the images as they arrive. ``margin_m`` grows the visited
    region in which poses are proposed, or ``box`` = ((x, y, z), (x, y, z)) bounds it (base frame, m).
    ``next_pose_format``: how ``next_poses.csv`` writes them (``live/poses.py``: ``header()``,
    ``row(name, base_T_ee)``, ``describe()``; a ``PoseFiles`` writes them as its files hold poses), by
    default as the dataset's ``robot_poses.csv``.
    """

    def __init__(self, dataset_dir, target_mm: float = 1.0, target_deg: float = 0.1, out=None,
                 predictions: str | None = None, opt: SolveOptions | None = None, k_next: int = K_NEXT,
                 margin_m: float = 0.05, box=None, cache_dir=None, guide: bool = True, seed: int = 0,
                 pixel_from_predictions: bool | None = None, next_pose_format=None):
        from calib3r_graph.live.poses import RobotPosesCsv
        from calib3r_graph.live.sources import IncrementalPairwise, RecordedPredictions

        self.ds = session_dataset(dataset_dir, name_bad_rows=True)
        self.poses_known = dict(self.ds.base_T_ee)  # the recording's, for frames added by id alone
        self.target = (float(target_mm), float(target_deg))
        self.out = Path(out) if out else None
        self.k_next, self.margin_m, self.box, self.guide, self.seed = k_next, margin_m, box, guide, seed
        self.next_pose_format = next_pose_format or RobotPosesCsv(
            Path(self.ds.meta.get("robot", {}).get("poses", "robot_poses.csv")), self.ds.robot_unit)
        if predictions:
            from calib3r_graph.io.predictions import load_predictions

            preds = load_predictions(self.ds.root, predictions, self.ds.cameras, None)
            self.source = RecordedPredictions(preds)
        else:
            self.source = IncrementalPairwise(cache_dir=cache_dir or (self.out / "cache" if self.out else None))
        # the match noise: the predictions' info.json match_noise_px (the pairwise frontend's, per update),
        # as solve reads it, unless the options were given with it
        self.pixel_from_predictions = opt is None if pixel_from_predictions is None else pixel_from_predictions
        opt = opt or SolveOptions()
        self.opt = dataclasses.replace(opt, progress=False)
        self.engine = Engine(self.ds, self.opt)
        self.base_T_ee = {}  # frames used, in arrival order
        self.step = 0
        self.last: Update | None = None
        self.sol = None
        self.preds = None
        self.image_root = None

    # ------------------------------------------------------------------ frames
    def add_frame(self, frame_id: str, base_T_ee=None, images: dict | None = None) -> Update:
        """Add a frame and update. ``base_T_ee``: 4x4 (metres) or gtsam.Pose3; None takes the
        dataset's row for ``frame_id``. ``images``: {camera: path or HxWx3 uint8}; None takes the
        dataset's files."""
        t0, self._c0 = time.perf_counter(), time.process_time()
        self.step += 1
        frame_id = str(frame_id)
        skipped = []
        try:
            pose = self._pose(frame_id, base_T_ee)
            if images:
                self._store_images(frame_id, images)
            self._check_images(frame_id)
        except InputError as e:
            skipped.append((frame_id, str(e)))
            return self._emit(self._carry(skipped, t0))
        self.base_T_ee[frame_id] = pose
        ds = self._dataset()
        try:
            self.source.add(ds, frame_id)
        except (Calib3rError, OSError, ValueError) as e:  # an image the frontend cannot use
            del self.base_T_ee[frame_id]
            skipped.append((frame_id, f"{type(e).__name__}: {e}"))
            return self._emit(self._carry(skipped, t0))
        return self._emit(self._solve(final=False, skipped=skipped, t0=t0))

    def frame_ready(self, frame) -> bool:
        """Whether the dataset folder holds what the frame needs: its predictions (a recording's) or an
        image per camera."""
        from calib3r_graph.live.sources import RecordedPredictions

        if isinstance(self.source, RecordedPredictions):
            return bool(self.source.frame_views(frame))
        return all(self.ds.image_path(c, frame) for c in self.ds.cameras)

    def skip(self, frame_id: str, reason: str) -> Update:
        """Name a frame that cannot be used (e.g. its pose row does not parse); nothing else changes."""
        self.step += 1
        return self._emit(self._carry([(str(frame_id), reason)], time.perf_counter()))

    def resume_frames(self, frames: list) -> Update | None:
        """Re-add frames a killed session had used ([(frame, base_T_ee 4x4)]), with one solve."""
        t0, self._c0 = time.perf_counter(), time.process_time()
        for f, T in frames:
            self.base_T_ee[str(f)] = self._pose(str(f), T)
            self.source.add(self._dataset(), str(f))
        if not frames:
            return None
        self.step += 1
        return self._emit(self._solve(final=False, skipped=[], t0=t0))

    def finish(self) -> Update:
        """``solve``'s full schedule on every frame so far (its result, warm-started) and the final
        outputs."""
        t0, self._c0 = time.perf_counter(), time.process_time()
        self.step += 1
        return self._emit(self._solve(final=True, skipped=[], t0=t0))

    # ------------------------------------------------------------------ internals
    def _dataset(self) -> Dataset:
        root = self.image_root or self.ds.root
        return dataclasses.replace(self.ds, root=root, base_T_ee={f: self.base_T_ee[f] for f in self._ordered()})

    def _ordered(self) -> list:
        """Frames in the dataset's order (the batch frontend's pair order), then new ones by arrival."""
        known = [f for f in self.poses_known if f in self.base_T_ee]
        return known + [f for f in self.base_T_ee if f not in self.poses_known]

    def _pose(self, frame, base_T_ee) -> gtsam.Pose3:
        if base_T_ee is None:
            if frame not in self.poses_known:
                raise InputError(f"frame {frame}", "no robot pose")
            return self.poses_known[frame]
        M = base_T_ee.matrix() if isinstance(base_T_ee, gtsam.Pose3) else np.asarray(base_T_ee, float)
        if M.shape != (4, 4) or not np.all(np.isfinite(M)):
            raise InputError(f"frame {frame}", "robot pose is not a finite 4x4 matrix")
        R = M[:3, :3]
        if abs(np.linalg.det(R) - 1) > 1e-3 or np.abs(R.T @ R - np.eye(3)).max() > 1e-3:
            raise InputError(f"frame {frame}", "robot pose's rotation is not a rotation matrix")
        return gtsam.Pose3(M)

    def _store_images(self, frame, images):
        """Images given as arrays (or paths elsewhere) are written into OUT/images/<camera>/<frame>.png,
        the session's own image folder."""
        import cv2

        if self.out is None:
            raise InputError("images", "LiveSession needs out=... to keep images given as arrays")
        self.image_root = self.out
        for cam, img in images.items():
            if cam not in self.ds.cameras:
                raise InputError(f"frame {frame}", f"unknown camera '{cam}'")
            if isinstance(img, (str, Path)):
                arr = cv2.imread(str(img), cv2.IMREAD_COLOR)
                if arr is None:
                    raise InputError(img, "cannot read the image")
            else:
                arr = np.asarray(img)
                if arr.dtype != np.uint8 or arr.ndim not in (2, 3):
                    raise InputError(f"frame {frame}", f"image for {cam} must be HxW or HxWx3 uint8")
                arr = arr[..., ::-1] if arr.ndim == 3 else arr  # RGB in, OpenCV writes BGR
            path = self.out / "images" / cam / f"{frame}.png"
            path.parent.mkdir(parents=True, exist_ok=True)
            ok, buf = cv2.imencode(".png", np.ascontiguousarray(arr))
            path.write_bytes(buf.tobytes())

    def _check_images(self, frame):
        """With the pairwise frontend every camera's image must exist and be readable at its size."""
        from calib3r_graph.live.sources import RecordedPredictions

        if isinstance(self.source, RecordedPredictions):
            if not self.source.frame_views(frame):
                raise InputError(f"frame {frame}", "no predictions for this frame")
            return
        import cv2

        root = self.image_root or self.ds.root
        ds = dataclasses.replace(self.ds, root=root)
        for name, cam in self.ds.cameras.items():
            p = ds.image_path(name, frame)
            if p is None:
                raise InputError(root / "images" / name / frame, "no image for this frame")
            img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise InputError(p, "cannot read the image")
            if img.shape != (cam.height, cam.width):
                raise InputError(p, f"image is {img.shape[1]}x{img.shape[0]}, camera {name} is "
                                    f"{cam.width}x{cam.height}")

    def _carry(self, skipped, t0) -> Update:
        """The previous update's state, with the skipped frame named (nothing is lost)."""
        last = self.last
        up = Update(self.step, list(self.base_T_ee), time.perf_counter() - t0, {}, skipped=skipped)
        if last is not None:
            for f in ("ee_T_cam", "sigma_ee_frame", "metric_scale", "next_poses", "next_kinds", "done", "floor",
                      "sigma_checked", "calibration"):
                setattr(up, f, getattr(last, f))
        up.message = "frame skipped"
        return up

    def _solve(self, final, skipped, t0) -> Update:
        from calib3r_graph.solver.guidance import candidate_poses, score_candidates

        ds = self._dataset()
        frames = list(ds.base_T_ee)
        tf = time.perf_counter()
        try:
            preds = (self.source.final if final else self.source.predictions)(ds, frames)
        except Calib3rError as e:  # e.g. no two images matched yet
            up = Update(self.step, frames, time.perf_counter() - tf, dict(self.source.seconds), skipped=skipped)
            up.message = f"waiting: {e}"
            return up
        front = dict(self.source.seconds)
        t1, c1 = time.perf_counter(), time.process_time()
        front["aggregation"] = t1 - tf - front.get("rescue", 0.0)  # robot-guided matching: pair geometry
        up = Update(self.step, frames, 0.0, front, skipped=skipped, frontend_cpu_s=c1 - self._c0)
        if self.pixel_from_predictions and "match_noise_px" in preds.info:
            noise = dataclasses.replace(self.engine.opt.noise, pixel_sigma_px=float(preds.info["match_noise_px"]))
            self.engine.opt = dataclasses.replace(self.engine.opt, noise=noise)
        try:
            sol = (self.engine.finish if final else self.engine.update)(ds.base_T_ee, preds)
        except Calib3rError as e:
            up.latency_s, up.cpu_s = time.perf_counter() - t1, time.process_time() - c1
            up.message = f"waiting: {e}"
            return up
        self.sol, self.preds = sol, preds
        up.ee_T_cam = {c: X.matrix().tolist() for c, X in sol.ee_T_cam.items()}
        up.sigma_ee_frame = {c: uncertainty_report(X, sol.covariance[c])["sigma_ee_frame"]
                             for c, X in sol.ee_T_cam.items()}
        up.metric_scale = dict(sol.metric_scale)
        mm, deg = up.largest()
        poses = len(sol.frames)
        up.sigma_checked = poses >= MIN_CHECKED_POSES
        within = mm <= self.target[0] and deg <= self.target[1]
        up.done = within and up.sigma_checked
        up.floor = self._floor(sol)
        if up.done:
            up.message = f"done: largest sigma {mm:.2f} mm / {deg:.3f} deg within {self.target[0]} mm / {self.target[1]} deg"
        elif within:
            up.message = (f"the sigma is within the target, but {poses} robot poses are too few to check it: "
                          f"add poses up to {MIN_CHECKED_POSES}")
        elif up.floor:
            up.message = ("more poses will not help: the robot's systematic error alone gives more than the target "
                          f"{self.target[0]} mm / {self.target[1]} deg")
        if final:  # the status line says which result this is
            up.message = "; ".join(m for m in (f"final: solve on all {len(frames)} frames", up.message) if m)
        tg = time.perf_counter()
        if self.guide and not up.done:
            try:
                cands = candidate_poses(sol, ds.base_T_ee, self.margin_m, self.box, np.random.default_rng(self.seed))
                ranked = score_candidates(sol, preds, self.engine.last_noise, ds.base_T_ee,
                                          [(k, E, None) for k, E in cands], *self.target,
                                          information=self.engine.last_information)
                up.next_poses = [p.base_T_ee.matrix().tolist() for p in ranked[:self.k_next]]
                up.next_kinds = [p.kind for p in ranked[:self.k_next]]
            except (ValueError, np.linalg.LinAlgError, RuntimeError) as e:  # no scene points yet, ...
                log.info("no guidance this update: %s", e)
        up.guidance_s = time.perf_counter() - tg
        up.calibration = calibration_json(sol, preds.name)
        if self.engine.note:  # e.g. a warm update solved again from scratch (engine.LOST_ROBOT_F)
            up.message = "; ".join(m for m in (up.message, self.engine.note) if m)
        up.latency_s, up.cpu_s = time.perf_counter() - t1, time.process_time() - c1
        return up

    def next_pose_rows(self, up) -> list:
        """``next_poses.csv``'s rows of an update, header first: its proposed poses as
        ``next_pose_format`` writes them, named next01, next02, ..."""
        fmt = self.next_pose_format
        return [fmt.header()] + [fmt.row(f"next{i + 1:02d}", T) for i, T in enumerate(up.next_poses)]

    def _floor(self, sol) -> bool:
        """The systematic part alone exceeds the target even at the best motion: it does not average
        out with more poses, and better rotations only lower its geometric gain (uncertainty.
        systematic_error_gain, mm per mm) towards about 1, so the floor is the systematic sigma over
        that gain where the gain is above 1."""
        gain = max(1.0, float(sol.stats.get("systematic_error_gain", {}).get("mm_per_mm", 1.0)))
        for c, X in sol.ee_T_cam.items():
            s = sol.systematic.get(c)
            if s is None or not s.measured:
                continue
            C = covariance_in_ee_frame(X, s.covariance) / gain**2
            mm, deg = largest_sigma({c: sigma_ee_frame(np.sqrt(np.maximum(np.diag(C), 0)))})
            if mm > self.target[0] or deg > self.target[1]:
                return True
        return False

    def _emit(self, up: Update) -> Update:
        self.last = up
        if self.out is not None:
            self.out.mkdir(parents=True, exist_ok=True)
            path = self.out / "live.jsonl"
            old = path.read_text() if path.is_file() else ""
            atomic_write_text(path, old + json.dumps(up.to_json()) + "\n")
            if up.calibration is not None:
                atomic_write_json(self.out / "calibration.json", up.calibration)
            atomic_write_text(self.out / "next_poses.csv", "\n".join(",".join(r) for r in self.next_pose_rows(up)) + "\n")
        return up
