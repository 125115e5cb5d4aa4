"""Where ``live --watch`` reads the robot poses of the frames a capture script adds.

* :class:`RobotPosesCsv`: the dataset's own pose file (``dataset.yaml``'s ``robot.poses``, usually
  ``robot_poses.csv``), row by row (:func:`read_pose_rows`).
* :class:`PoseFiles`: any pose file that ``import files`` reads (``io/pose_files.py``: one file per
  frame, JSON/YAML/CSV/text/.npy, in a folder or glob, or one file with a pose per line or entry),
  with ``--pose-format``, ``--pose-key``, ``--unit`` and ``--direction`` as there. The frame id is
  the pose's number as ``import files`` writes it (``0007`` for ``pose_7.json`` or a frame column of
  7; by order where nothing is numbered), so the images go to ``images/<camera>/0007.png``.

``poll()`` returns ``[(frame, base_T_ee 4x4 in metres or None, reason)]`` for every pose readable
now; a pose that cannot be used (NaN, not a rotation, wrong count of numbers) has None and the
reason naming its file and line. A per-frame file that does not parse yet may be half written: it is
named and skipped only once it stops changing (same size and time over two polls).

Both also write the poses the guidance proposes as the poses came (``next_poses.csv``): ``header()``
and ``row(name, base_T_ee)``, so that a user can hand them to the robot in its own format, unit and
direction (a KUKA's ``x y z a b c`` in mm and degrees, say), and ``describe()`` says which.
"""

import csv
import tempfile
from pathlib import Path

import gtsam
import numpy as np

from calib3r_graph.errors import InputError
from calib3r_graph.io.dataset import ROBOT_COLUMNS, UNIT_TO_METRES, pose_to_row, read_robot_poses
from calib3r_graph.io.pose_files import (PER_FRAME_SUFFIXES, column_names, expand, frame_numbers, layout_of,
                                         parse_format, read_poses, to_numbers)

STRUCTURED = (".npy", ".json", ".yaml", ".yml")


class RobotPosesCsv:
    """A last row without its line end may be half written (a capture script's write caught mid-way,
    which can cut a number and still parse): it is read only once the file has not changed over two
    polls."""

    def __init__(self, path: Path, unit: str):
        self.path, self.unit = Path(path), unit
        self._tail = {}  # the file -> (size, mtime) when its last line was last seen without a line end

    def poll(self) -> list:
        text = settled_text(self.path, self._tail)
        return [] if text is None else read_pose_rows(self.path, self.unit, text)

    def header(self) -> list:
        return list(ROBOT_COLUMNS)

    def row(self, name: str, base_T_ee) -> list:
        """A base_T_ee (4x4, metres) as a robot_poses.csv row in this file's unit."""
        return pose_to_row(name, gtsam.Pose3(np.asarray(base_T_ee, dtype=float)), 1.0 / UNIT_TO_METRES[self.unit])

    def describe(self) -> str:
        return f"as {self.path.name}: x y z qx qy qz qw, {self.unit}"


def read_pose_rows(path: Path, unit: str, text: str) -> list:
    """[(frame, base_T_ee 4x4 or None, reason)] of every row of ``text``, a robot_poses.csv being
    written at ``path``: a row that does not parse (NaN, not unit, too few columns) is named with its
    reason instead of failing the whole file, as ``read_robot_poses`` would (each row goes through it
    alone)."""
    lines = text.splitlines()
    out = []
    for i, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        frame = next(csv.reader([line]))[0].strip()
        with tempfile.TemporaryDirectory() as tmp:
            one = Path(tmp) / "row.csv"
            one.write_text(lines[0] + "\n" + line + "\n")
            try:
                pose = read_robot_poses(one, unit, "a row")
                out.append((frame, next(iter(pose.values())).matrix(), None))
            except InputError as e:
                out.append((frame, None, f"{path}: row {i} (frame {frame}): {e.what}"))
    return out


def read_text(p: Path) -> tuple:
    """(the file's text, its (size, mtime) when read), or (None, None) where it is not there."""
    try:
        st = p.stat()
        return p.read_text(encoding="utf-8-sig"), (st.st_size, st.st_mtime_ns)
    except (OSError, UnicodeDecodeError):
        return None, None


def settled_text(p: Path, seen: dict) -> str | None:
    """The file's text (None where it is not there), without a last line that has no line end yet
    unless the file has not changed since the last call for it (``seen``: each file's (size, mtime)
    then): a line caught mid-write is read once whole or once the file has settled."""
    text, stat = read_text(p)
    if text is not None and open_tail(text) and not _settled(seen, p, stat):
        text = "".join(text.splitlines(keepends=True)[:-1])
    return text


def open_tail(text: str) -> bool:
    """Whether the text's last line has content and no line end yet."""
    return bool(text) and not text.endswith(("\n", "\r")) and bool(text.splitlines()[-1].strip())


def _settled(seen: dict, f: Path, now=None) -> bool:
    """Whether ``f`` has not changed since the last call for it (not half written): ``seen`` keeps each
    file's (size, mtime) from that call; ``now``: its (size, mtime) where already known."""
    if now is None:
        try:
            st = f.stat()
        except OSError:
            return False
        now = (st.st_size, st.st_mtime_ns)
    before = seen.get(f)
    seen[f] = now
    return before == now


class PoseFiles:
    def __init__(self, spec: str, pose_format: str | None = None, pose_key: str | None = None, unit: str = "m",
                 direction: str = "base_T_ee"):
        if pose_format is None and not pose_key:
            from calib3r_graph.io.pose_files import FORMAT_HELP

            raise InputError("--pose-format", f"give the pose files' format: {FORMAT_HELP}")
        self.spec, self.fmt, self.key = str(spec), parse_format(pose_format or "matrix"), pose_key
        self.unit, self.direction = unit, direction
        self._failed = {}  # file -> (size, mtime) when it last failed to parse
        self._tail = {}  # file -> (size, mtime) when its last line was last seen without a line end
        self.layout = "row-major"  # a 4x4's numbers as the files read so far hold them

    def header(self) -> list:
        return ["frame", *column_names(self.fmt, self.layout)]

    def row(self, name: str, base_T_ee) -> list:
        """A base_T_ee (4x4, metres) as this file's numbers: its format (a 4x4 in its layout), unit and
        direction; :meth:`poll` reads such numbers back to the same pose."""
        M = np.array(base_T_ee, dtype=float)
        if self.direction == "ee_T_base":
            M = np.linalg.inv(M)
        M[:3, 3] /= UNIT_TO_METRES[self.unit]
        return [name, *(f"{v:.10g}" for v in to_numbers(M, self.fmt, self.layout))]

    def describe(self) -> str:
        layout = f", {self.layout}" if self.fmt.name == "matrix" else ""
        return f"as {Path(self.spec).name}: {self.fmt.name}{layout}, {self.unit}, {self.direction}"

    def _read(self, spec) -> list:
        recs = read_poses(str(spec), self.fmt, self.key)
        self.layout = layout_of([r for r in recs if len(r.layouts) == 1]) or self.layout  # (not one that fits both)
        return recs

    def _base_T_ee(self, M) -> np.ndarray:
        from calib3r_graph.importers import DIRECTIONS, apply_convention

        return apply_convention(M, self.unit, DIRECTIONS[self.direction]).matrix()

    def _frame(self, number, index) -> str:
        return f"{number if number is not None else index:04d}"  # as import files names the frames

    def poll(self) -> list:
        p = Path(self.spec)
        if p.is_file():
            return self._one_file(p)
        if not p.is_dir() and not any(ch in self.spec for ch in "*?["):
            return []  # the folder is not there yet
        files = expand(self.spec, PER_FRAME_SUFFIXES)
        numbers = frame_numbers(files) or [None] * len(files)
        out = []
        for i, (f, n) in enumerate(zip(files, numbers)):
            frame = self._frame(n, i)
            try:
                recs = self._read(f)
                if len(recs) != 1:
                    raise InputError(f, f"one file per frame should hold one pose, this one holds {len(recs)}")
                out.append((frame, self._base_T_ee(recs[0].matrix), None))
                self._failed.pop(f, None)
            except InputError as e:
                if self._settled(f):
                    out.append((frame, None, f"{e.path}: {e.what}"))
        return out

    def _settled(self, f: Path) -> bool:
        """Whether a file that failed to parse has not changed since it last failed (not half written)."""
        return _settled(self._failed, f)

    def _one_file(self, p: Path) -> list:
        """One file of every frame's pose: read whole; where that fails, a text file line by line (each
        line through the same reader, so one bad line skips one frame), else nothing until it changes.
        A text file's last line without its line end waits as :class:`RobotPosesCsv`'s does."""
        if p.suffix.lower() in STRUCTURED:
            try:
                recs = self._read(p)
                return [(self._frame(r.number, i), self._base_T_ee(r.matrix), None) for i, r in enumerate(recs)]
            except InputError as e:
                return [] if not self._settled(p) else [(str(p), None, f"{e.path}: {e.what}")]
        text = settled_text(p, self._tail)
        if text is None:
            return []
        with tempfile.TemporaryDirectory() as tmp:
            copy = Path(tmp) / p.name  # the text as read now, so the whole read and the lines agree
            copy.write_text(text)
            try:
                recs = self._read(copy)
                return [(self._frame(r.number, i), self._base_T_ee(r.matrix), None) for i, r in enumerate(recs)]
            except InputError:
                pass
        out = []
        lines = text.splitlines()
        with tempfile.TemporaryDirectory() as tmp:
            one = Path(tmp) / f"line{p.suffix}"
            index = 0
            for i, line in enumerate(lines, start=1):
                body = line.split("#", 1)[0].strip()
                if not body or not any(ch.isdigit() for ch in body):
                    continue  # a comment or a header
                one.write_text(line + "\n")
                try:
                    rec = self._read(one)[0]
                    out.append((self._frame(rec.number, index), self._base_T_ee(rec.matrix), None))
                except (InputError, IndexError) as e:
                    first = body.replace(",", " ").split()[0]
                    frame = f"{int(first):04d}" if first.isdigit() else self._frame(None, index)
                    what = e.what if isinstance(e, InputError) else "no pose"
                    out.append((frame, None, f"{p}: line {i}: {what}"))
                index += 1
        return out
