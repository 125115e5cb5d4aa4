"""What ``calib3r-graph live`` runs: a recorded dataset replayed frame by frame (recorded, guided or
random order), or a dataset folder watched for the frames a capture script adds."""

import json
import logging
import time
from pathlib import Path

import numpy as np

from calib3r_graph.errors import InputError
from calib3r_graph.live.session import LiveSession, Update, read_pose_rows

log = logging.getLogger(__name__)


def replay(session: LiveSession, order: str, seed: int = 0, on_update=None, stop_at_target=False) -> list:
    """Replay the session's recording. ``order``: "recorded", "random" (seeded permutation) or
    "guided": the next frame is the unused recorded frame that the guidance scores best (the
    recording's poses are the reachable set); before the first solve, the unused frame whose
    flange rotation differs most from those used. Ends with :meth:`LiveSession.finish`."""
    from calib3r_graph.solver.plan import score_candidates

    frames = list(session.poses_known)
    if order == "recorded":
        todo = list(frames)
    elif order == "random":
        todo = list(np.random.default_rng(seed).permutation(frames))
    elif order == "guided":
        todo = None
    else:
        raise InputError("--replay", f"'{order}' is not recorded, guided or random")
    updates, used = [], []
    nxt = frames[0] if todo is None else None
    while True:
        f = todo.pop(0) if todo is not None else nxt
        if f is None:
            break
        up = session.add_frame(f)
        used.append(f)
        updates.append(up)
        if on_update:
            on_update(up)
        if stop_at_target and up.done:
            break
        if todo is None:
            rest = [g for g in frames if g not in used]
            if not rest:
                break
            nxt = None
            if session.sol is not None and up.ee_T_cam and f in session.base_T_ee:
                try:
                    ranked = score_candidates(session.sol, session.preds, session.engine.last_noise,
                                              session._dataset().base_T_ee,
                                              [("recorded", session.poses_known[g], g) for g in rest], *session.target,
                                              information=session.engine.last_information)
                    nxt = ranked[0].frame
                except (ValueError, np.linalg.LinAlgError, RuntimeError) as e:
                    log.info("guided: no score (%s); the most different rotation instead", e)
            if nxt is None:
                nxt = _most_different(session, used, rest)
        elif not todo:
            break
    if len(session.base_T_ee) >= 3:
        up = session.finish()
        updates.append(up)
        if on_update:
            on_update(up)
    return updates


def _most_different(session, used, rest):
    """The unused frame whose flange orientation is farthest from every used one."""
    import gtsam

    R = [session.poses_known[f].rotation() for f in used if f in session.poses_known]

    def nearest(g):
        Rg = session.poses_known[g].rotation()
        return min((np.linalg.norm(gtsam.Rot3.Logmap(r.between(Rg))) for r in R), default=0.0)

    return max(rest, key=nearest)


def watch(session: LiveSession, poll_s: float = 1.0, on_update=None, max_idle_s: float | None = None,
          resume: bool = False) -> Update | None:
    """Poll the dataset folder for frames: a row in the robot pose file and an image per camera.
    Each complete frame is added once, in the file's order; a bad row is named and skipped. Ends at
    the target (``done``) or when nothing new came for ``max_idle_s``; Ctrl-C ends it too, with
    everything written after each update already in place."""
    ds = session.ds
    poses_file = ds.root / ds.meta["robot"]["poses"]
    seen = set()
    if resume and session.out is not None and (session.out / "live.jsonl").is_file():
        lines = [json.loads(x) for x in (session.out / "live.jsonl").read_text().splitlines() if x.strip()]
        done_frames = lines[-1]["frames"] if lines else []
        rows = {f: T for f, T, _ in read_pose_rows(poses_file, ds.robot_unit) if T is not None}
        session.step = lines[-1]["step"] if lines else 0
        up = session.resume_frames([(f, rows[f]) for f in done_frames if f in rows])
        if up is not None and on_update:
            on_update(up)
        seen.update(done_frames)
        for x in lines:
            seen.update(s[0] for s in x.get("skipped", []))
    last_new = time.monotonic()
    up = session.last
    while True:
        got = False
        for frame, T, reason in read_pose_rows(poses_file, ds.robot_unit):
            if frame in seen:
                continue
            if T is None:
                seen.add(frame)
                up = session.skip(frame, reason)
            else:
                if not session.frame_ready(frame):
                    continue  # its images (or predictions) are not all there yet
                seen.add(frame)
                up = session.add_frame(frame, T)
            got = True
            if on_update:
                on_update(up)
            if up.done:
                return up
        if got:
            last_new = time.monotonic()
        elif max_idle_s is not None and time.monotonic() - last_new > max_idle_s:
            return up
        time.sleep(poll_s)
