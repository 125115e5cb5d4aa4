"""``import files``: a folder of images per camera and a robot pose file -> calib3r-dataset/1.

Frames are matched to poses by the number in the image file names (and in the pose file's
frame column or per-frame file names; where the names do not tell the frames apart, as in
per-frame folders ``pose_07/image.png``, by the nearest parent folder's number), or else by
sorted order; any mismatch is an error. dataset.yaml's ``source.frames`` keeps, per frame id,
the image file of each camera and where its pose was read.
With a board in the images, the pose direction (base_T_ee or ee_T_base) and unit (m or mm)
are checked against the board's visual motion, as ``import rwhe`` does, and the convention the
images support is used and reported. Intrinsics come from a file
(calib3r_graph.io.intrinsics_files) or are calibrated from the board.
"""

import logging
import shutil
from pathlib import Path

import cv2

from calib3r_graph.errors import InputError
from calib3r_graph.importers import (DIRECTION_KEYS, DIRECTIONS, apply_convention, board_poses, calibrate_intrinsics,
                                     choose_convention, convention_lines, detect_all,
                                     refine_intrinsics_with_robot, turns_record, unturned)
from calib3r_graph.io import board_turns, boards
from calib3r_graph.io.dataset import opencv_camera, write_dataset_yaml, write_robot_poses
from calib3r_graph.io.intrinsics_files import read_intrinsics
from calib3r_graph.io.output import staged_directory
from calib3r_graph.io.pose_files import FORMAT_HELP, describe, expand, frame_numbers, parse_format, read_poses

log = logging.getLogger(__name__)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
KEEP_SUFFIXES = (".png", ".jpg", ".jpeg")  # the dataset reads these as they are


def _numbered(items, number_of):
    """The items' numbers if every item has one and none repeats, else None."""
    nums = [number_of(x) for x in items]
    return nums if all(n is not None for n in nums) and len(set(nums)) == len(nums) else None


def match_frames(image_lists: list, records: list) -> tuple:
    """``(frames, {frame: pose record}, [{frame: image path}] per camera, how)``.

    By number where the poses and the images are numbered, else by sorted order."""
    pose_nums = _numbered(records, lambda r: r.number)
    cams_nums = [frame_numbers(files) for files in image_lists]
    if pose_nums is not None and all(n is not None for n in cams_nums):
        poses = dict(zip(pose_nums, records))
        out = []
        for files, nums in zip(image_lists, cams_nums):
            by_num = dict(zip(nums, files))
            missing, extra = sorted(set(pose_nums) - set(nums)), sorted(set(nums) - set(pose_nums))
            if missing or extra:
                folder = files[0].parent
                what = (f"frame(s) {_few(extra)} have no pose" if extra else "") + \
                    ("; " if missing and extra else "") + (f"pose(s) {_few(missing)} have no image" if missing else "")
                raise InputError(folder, f"{len(files)} images but {len(records)} poses, matched by the number in "
                                         f"the file names: {what}")
            out.append({f"{n:04d}": by_num[n] for n in sorted(pose_nums)})
        return [f"{n:04d}" for n in sorted(pose_nums)], {f"{n:04d}": poses[n] for n in pose_nums}, out, "by number"
    out = []
    for files, nums in zip(image_lists, cams_nums):
        if len(files) != len(records):
            raise InputError(files[0].parent, f"{len(files)} images but {len(records)} poses (matched in sorted order, "
                                              "since not both are numbered): the counts must agree")
        ordered = [f for _, f in sorted(zip(nums, files))] if nums is not None else files
        out.append({f"{i:04d}": f for i, f in enumerate(ordered)})
    if pose_nums is not None:
        records = [r for _, r in sorted(zip(pose_nums, records), key=lambda x: x[0])]
    frames = [f"{i:04d}" for i in range(len(records))]
    return frames, dict(zip(frames, records)), out, "in sorted order"


def _few(nums, k=5) -> str:
    return ", ".join(str(n) for n in nums[:k]) + (f" and {len(nums) - k} more" if len(nums) > k else "")


def _image_size(path: Path) -> tuple:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(path, "unreadable image")
    return img.shape[1], img.shape[0]


def _cameras_intrinsics(intrinsics_files: list, n_cams: int, sizes: list, camera_name=None) -> list:
    one_each = len(intrinsics_files) == n_cams  # then file j is camera j's: its image size picks among several
    found = [i for j, f in enumerate(intrinsics_files)
             for i in read_intrinsics(f, camera_name, sizes[j] if one_each else None)]
    if len(found) != n_cams:
        raise InputError("--intrinsics", f"{len(found)} camera(s) in the intrinsics file(s) but {n_cams} --images "
                                         "folder(s): give one per camera, in the same order")
    for intr, size in zip(found, sizes):
        if intr.width is not None and (intr.width, intr.height) != size:
            raise InputError(intr.source, f"intrinsics are for {intr.width}x{intr.height} images but the images are "
                                          f"{size[0]}x{size[1]}")
    return found


def import_files(dst, images: list, poses: str, pose_format: str | None, unit: str | None = None,
                 intrinsics: list | None = None, board: str | None = None, progress: bool = True,
                 pose_key: str | None = None, camera_name: str | None = None, direction: str | None = None) -> str:
    """Write a dataset to ``dst``; returns the report. ``pose_key``: the JSON/YAML entry holding
    each pose (then ``pose_format`` defaults to matrix); ``camera_name``: a ViSP camera.xml's camera."""
    dst = Path(dst)
    if pose_format is None and not pose_key:
        raise InputError("--pose-format", f"give the pose files' format: {FORMAT_HELP}")
    fmt = parse_format(pose_format or "matrix")
    if not intrinsics and not board:
        raise InputError("--intrinsics", "give the cameras' intrinsics (--intrinsics FILE) or a board in the images "
                                         "to calibrate them from (--board SPEC)")
    image_lists = []
    for spec in images:
        files = expand(spec, IMAGE_SUFFIXES)
        if not files:
            raise InputError(spec, f"no images ({', '.join(IMAGE_SUFFIXES)}) in it")
        image_lists.append(files)
    records = read_poses(poses, fmt, pose_key)
    frames, pose_of, image_of, how = match_frames(image_lists, records)
    sizes = []
    for j, files in enumerate(image_of):
        size = _image_size(next(iter(files.values())))
        sizes.append(size)
    given = _cameras_intrinsics(intrinsics, len(images), sizes, camera_name) if intrinsics else None
    mats = {f: pose_of[f].matrix for f in frames}
    lines = [f"imported {len(frames)} frames x {len(images)} camera(s) into {dst}, images matched to poses {how}"]
    if describe(records):
        lines.append(f"  robot poses: {describe(records)}")

    board_obj, pattern, cams, convention = None, None, [], None
    if board:
        board_obj = boards.parse_board(board)
        if board_obj.size is None:
            raise InputError("--board", f"give the square size in metres too, e.g. --board "
                                        f"{board_obj.cols}x{board_obj.rows}:0.03")
    detections = []
    for j, files in enumerate(image_of):
        dets, board_used, K, dist, rms, cam_T_board = {}, board_obj, None, None, None, {}
        if board_obj is not None:
            try:
                dets, board_used, _ = detect_all(list(files.items()), board_obj, progress)
            except InputError:
                if given is None:
                    raise
                dets = {}
        if given is not None:
            K, dist = given[j].K, given[j].dist
            cam_T_board = board_poses(dets, board_used, K, dist) if dets else {}
            lines.append(f"  cam{j}: intrinsics from {given[j].source}")
        else:
            K, dist, rms, cam_T_board = calibrate_intrinsics(dets, board_used, sizes[j])
            lines.append(f"  cam{j}: intrinsics from the {board_used.describe()} in {len(dets)} images: "
                         f"fx {K[0, 0]:.1f} fy {K[1, 1]:.1f} cx {K[0, 2]:.1f} cy {K[1, 2]:.1f}, RMS {rms:.3f} px")
        if board_used is not None and dets:
            board_obj = board_used  # the dictionary found, or the checkerboard's corrected size
        detections.append((dets, cam_T_board, K, dist))

    # --- pose convention: checked against the board's motion, forced by --unit/--direction ---
    declared = f"{'--unit' if unit else 'the default unit'}, {'--direction' if direction else 'the default direction'}"
    unit_key, dir_key = unit or "m", direction or "base_T_ee"
    checked = [j for j, (d, cb, _, _) in enumerate(detections) if len(cb) >= 3]
    for j in checked:  # the first camera chooses, the others are checked under its choice
        dets, cam_T_board, K, dist = detections[j]
        conv = choose_convention({f: mats[f] for f in cam_T_board}, cam_T_board,
                                 board_turns.pose_covariances(board_obj, dets, cam_T_board, K, dist), board_obj,
                                 unit if j == checked[0] else conv.unit,
                                 direction if j == checked[0] else DIRECTION_KEYS[conv.direction], poses,
                                 f"cam{j}'s images ({images[j]})", f"{how} of the images' and the poses' files")
        detections[j] = (*unturned(dets, cam_T_board, board_obj, conv.turns), K, dist)
        if j == checked[0]:
            unit_used, direction_used = conv.unit, conv.direction
            lines += convention_lines(conv, unit_key, dir_key, declared)
            convention = conv.name
            source_turns = turns_record(conv)
        elif conv.turns.turned:
            lines.append(f"  cam{j}: {len(conv.turns.turned)} board detections renumbered to agree with the "
                         "robot's motion")
    if not checked:
        unit_used, direction_used = unit_key, DIRECTIONS[dir_key]
        seen = max((len(cb) for _, cb, _, _ in detections), default=0)
        why = "no board given" if board_obj is None else f"the board is seen in {seen} image(s), 3 needed"
        convention = f"{direction_used}, {unit_used} ({why}: unchecked)"
        lines.append(f"  robot poses: {why}: the poses are taken as {dir_key} in {unit_used} ({declared}), "
                     "unchecked (give --board to check direction and unit)")
        source_turns = {}
    base_T_ee = {f: apply_convention(M, unit_used, direction_used) for f, M in mats.items()}
    if board_obj is not None:
        pattern = boards.to_pattern(board_obj)
    for j, (dets, cam_T_board, K, dist) in enumerate(detections):
        sigma = None  # given intrinsics carry no stated sigma (solve --intrinsics-sigma-px states one)
        if given is None:
            K_board = K
            K, dist, sigma = refine_intrinsics_with_robot(K, dist, sizes[j], dets, cam_T_board, base_T_ee, pattern,
                                                          with_sigma=True)
            lines.append(f"  cam{j}: refined with the robot's metric motion (pattern-ba): fx {K[0, 0]:.1f} "
                         f"fy {K[1, 1]:.1f} cx {K[0, 2]:.1f} cy {K[1, 2]:.1f} (board alone: fx {K_board[0, 0]:.1f})"
                         + ("" if sigma is None else ", 1-sigma fx fy cx cy " + " ".join(f"{x:.2f}" for x in sigma)
                            + " px"))
        cams.append(opencv_camera(f"cam{j}", sizes[j], K, dist, params_sigma=sigma))
    sources = {f: {**{c.name: str(files[f]) for c, files in zip(cams, image_of)}, "pose": pose_of[f].where}
               for f in frames}
    _write(dst, cams, image_of, base_T_ee, pattern,
           {"source": {"format": "files", "images": [str(i) for i in images], "poses": str(poses),
                       "pose_format": fmt.name, **({"pose_key": pose_key} if pose_key else {}),
                       "pose_convention": convention, **source_turns, "matched": how, "frames": sources}})
    return "\n".join(lines)


def _write(dst: Path, cams, image_of, base_T_ee, pattern, extra):
    with staged_directory(dst) as stage:
        for cam, files in zip(cams, image_of):
            folder = stage / "images" / cam.name
            folder.mkdir(parents=True)
            for f, p in files.items():
                suffix = p.suffix.lower()
                if suffix in KEEP_SUFFIXES:
                    shutil.copyfile(p, folder / f"{f}{'.jpg' if suffix == '.jpeg' else suffix}")
                elif not cv2.imwrite(str(folder / f"{f}.png"), cv2.imread(str(p), cv2.IMREAD_UNCHANGED)):
                    raise InputError(p, "cannot be converted to PNG")
        write_robot_poses(stage / "robot_poses.csv", base_T_ee, unit="m")
        write_dataset_yaml(stage, cams, unit="m", pattern=pattern, extra=extra)
