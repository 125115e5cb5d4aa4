"""What ``calib3r-graph live`` runs: a recorded dataset replayed frame by frame (recorded, guided or
random order), or a dataset folder watched for the frames a capture script adds."""

import json
import logging
import time

import numpy as np

from calib3r_graph.errors import InputError
from calib3r_graph.live.session import LiveSession, Update

log = logging.getLogger(__name__)


def replay(session: LiveSession, order: str | list, seed: int = 0, on_update=None, stop_at_target=False) -> list:
    """Replay the session's recording. ``order``: "recorded", "random" (seeded permutation),
    "guided": the next frame is the unused recorded frame that the guidance scores best (the
    recording's poses are the reachable set); before the first solve, the unused frame whose
    flange rotation differs most from those used; it starts from the first recorded frame, or with
    ``seed`` above 0 from a seeded random one (where a session starts decides much of its first
    frames, so one guided order is one draw); or a list of frame ids (a fixed order, e.g. an
    oracle's; frames it leaves out are not used). Ends with :meth:`LiveSession.finish`."""
    from calib3r_graph.solver.guidance import score_candidates

    frames = list(session.poses_known)
    if isinstance(order, (list, tuple)):
        todo = [str(f) for f in order]
        unknown = [f for f in todo if f not in session.poses_known]
        if unknown or len(set(todo)) != len(todo) or not todo:
            raise InputError("order", f"a fixed order must list recorded frames once each (unknown: {unknown[:3]})")
    elif order == "recorded":
        todo = list(frames)
    elif order == "random":
        todo = list(np.random.default_rng(seed).permutation(frames))
    elif order == "guided":
        todo = None
    else:
        raise InputError("--replay", f"'{order}' is not recorded, guided or random")
    updates, used = [], []
    nxt = None
    if todo is None:
        nxt = frames[0] if seed == 0 else frames[int(np.random.default_rng(seed).integers(len(frames)))]
    while True:
        f = todo.pop(0) if todo is not None else nxt
        if f is None:
            break
        up = session.add_frame(f)
        used.append(f)
        updates.append(up)
        rest = [g for g in frames if g not in used]
        if todo is None and rest and not (stop_at_target and up.done):
            tg = time.perf_counter()
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
            up.guidance_s += time.perf_counter() - tg  # the guidance over the recorded frames is this update's
        if on_update:
            on_update(up)
        if stop_at_target and up.done:
            break
        if (todo is None and not rest) or (todo is not None and not todo):
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
          resume: bool = False, poses=None, finish: bool = True) -> Update | None:
    """Poll the dataset folder for frames: a robot pose and an image per camera. ``poses``: where the
    poses come from (``live/poses.py``: any pose file ``import files`` reads); by default the
    dataset's robot pose file. Each complete frame is added once, in the poses' order; a pose that
    cannot be used is named and skipped. Ends at the target (``done``) or when nothing new came for
    ``max_idle_s``; Ctrl-C ends it too, with everything written after each update already in place.
    At the target or the idle end, with ``finish``, a last update runs ``solve`` on every frame
    (:meth:`LiveSession.finish`), so that what the session leaves is ``solve``'s result on the frames
    it recorded, as a replay's is, and not the last incremental update (on rwhe_kuka_1's images that
    was 0.43 mm / 0.034 deg from it, up to 0.84 of its sigma)."""
    from calib3r_graph.live.poses import RobotPosesCsv

    ds = session.ds
    poses = poses or RobotPosesCsv(ds.root / ds.meta["robot"]["poses"], ds.robot_unit)
    seen = set()
    if resume and session.out is not None and (session.out / "live.jsonl").is_file():
        lines = [json.loads(x) for x in (session.out / "live.jsonl").read_text().splitlines() if x.strip()]
        done_frames = lines[-1]["frames"] if lines else []
        rows = {f: T for f, T, _ in poses.poll() if T is not None}
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
        for frame, T, reason in poses.poll():
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
                return _finish(session, up, on_update) if finish else up
        if got:
            last_new = time.monotonic()
        elif max_idle_s is not None and time.monotonic() - last_new > max_idle_s:
            return _finish(session, up, on_update) if finish else up
        time.sleep(poll_s)


def _finish(session: LiveSession, up, on_update):
    """``solve`` on the session's frames where an update has solved them, else ``up`` as it is."""
    if session.sol is None:
        return up
    up = session.finish()
    if on_update:
        on_update(up)
    return up
