"""Live, guided calibration (calib3r_graph/live, solver/guidance.py, the linearised jackknife)."""

import json

import gtsam
import numpy as np
import pytest

from calib3r_graph.cli import main
from calib3r_graph.io.dataset import load_dataset, subset_dataset
from calib3r_graph.io.predictions import load_predictions, subset_predictions
from calib3r_graph.io.results import covariance_in_ee_frame
from calib3r_graph.live import LiveSession
from calib3r_graph.live.run import replay
from calib3r_graph.solver import jackknife as jk
from calib3r_graph.solver.graph import NoiseOptions
from calib3r_graph.solver.solve import SolveOptions, solve

SIM = dict(seed=5, frames=6, cameras=1, matches_per_pair=300)


def _z(X, ref, cov):
    """ee-frame error of X against ref, per axis, in units of cov's sigma."""
    d = gtsam.Pose3.Logmap(ref.between(X))
    R = X.rotation().matrix()
    return np.r_[R @ d[:3], R @ d[3:]] / np.sqrt(np.diag(covariance_in_ee_frame(X, cov)))


def test_replay_ends_at_the_batch_solve(simulated):
    root = simulated(**SIM)
    ds = load_dataset(root)
    preds = load_predictions(root, "sim", ds.cameras, set(ds.frames))
    # as the CLI's solve: the match noise from the predictions' info.json, as the session reads it
    ref = solve(ds, preds, SolveOptions(noise=NoiseOptions(pixel_sigma_px=preds.info["match_noise_px"]),
                                        progress=False))
    session = LiveSession(root, predictions="sim", guide=False)
    ups = replay(session, "random", seed=1)
    assert [u.message.startswith("waiting") for u in ups[:3]] == [True, True, False]
    for c, X in session.sol.ee_T_cam.items():  # the last step is solve itself
        assert np.all(np.abs(_z(X, ref.ee_T_cam[c], ref.covariance[c])) < 1e-6)
    # the warm incremental update with every frame, before it, is already within 0.2 sigma of it
    warm = ups[-2]
    assert len(warm.frames) == len(ds.frames) and warm.ee_T_cam and not warm.message.startswith("waiting")
    for c, T in warm.ee_T_cam.items():
        z = _z(gtsam.Pose3(np.array(T)), ref.ee_T_cam[c], ref.covariance[c])
        assert np.all(np.abs(z) < 0.2), z
    # a middle update is a real, finite calibration with a total sigma
    mid = ups[4]
    assert len(mid.frames) == 5 and all(np.isfinite(list(s.values())).all() for s in mid.sigma_ee_frame.values())


def test_linearised_jackknife_matches_the_re_solving_one(simulated):
    root = simulated(**SIM)
    ds = load_dataset(root)
    preds = load_predictions(root, "sim", ds.cameras, set(ds.frames))
    frames = ds.frames[:6]
    sub, sub_preds = subset_dataset(ds, frames), subset_predictions(preds, frames)
    sol = solve(sub, sub_preds, SolveOptions(progress=False, jackknife="never"))
    lin, _ = jk.linearised_jackknife(sol)
    saved = jk.METHOD
    try:
        jk.METHOD = "resolve"
        res, _ = jk.jackknife(sub, sub_preds, SolveOptions(progress=False), sol, solve, progress=False)
    finally:
        jk.METHOD = saved
    for c in lin:
        a, b = lin[c]["sigma_jackknife"], res[c]["sigma_jackknife"]
        ratios = np.array([a[k] / b[k] for k in a])
        assert np.all(np.abs(ratios - 1) < 0.2), ratios


def test_replay_writes_live_jsonl_and_calibration(simulated, tmp_path, capsys):
    root = simulated(**SIM)
    out = tmp_path / "live"
    assert main(["-q", "live", str(root), "--replay", "recorded", "--out", str(out), "--next", "3"]) == 0
    lines = [json.loads(x) for x in (out / "live.jsonl").read_text().splitlines()]
    assert [x["step"] for x in lines] == list(range(1, len(lines) + 1))
    calib = json.loads((out / "calibration.json").read_text())
    assert not any(x["cameras"] for x in lines[:2])  # two poses: nothing to solve yet
    for x in lines[2:]:
        assert {"step", "frames", "latency_s", "cameras", "next_poses", "done"} <= set(x)
        for c, cam in x["cameras"].items():
            assert np.asarray(cam["T_ee_cam"]).shape == (4, 4)
            assert set(cam["sigma_ee_frame"]) == set(calib["cameras"][c]["sigma_ee_frame"])
        if not x["done"]:  # at the target there is nothing more to propose
            assert np.asarray(x["next_poses"]).shape == (3, 4, 4)
    assert not lines[2]["done"]
    assert lines[-1]["frames"] == load_dataset(root).frames
    rows = (out / "next_poses.csv").read_text().splitlines()
    assert rows[0] == "frame,x,y,z,qx,qy,qz,qw" and len(rows) == 1 + len(lines[-1]["next_poses"])
    printed = capsys.readouterr().out
    assert f"frames {len(lines[-1]['frames']):3d}" in printed
    assert f"wrote {out}/calibration.json, next_poses.csv, live.jsonl\n" in printed
    # nothing the user had is overwritten: a second run into the same folder is refused
    assert main(["-q", "live", str(root), "--replay", "recorded", "--out", str(out)]) != 0


def test_a_bad_frame_is_named_and_skipped(simulated, tmp_path):
    root = simulated(**SIM)
    ds = load_dataset(root)
    out = tmp_path / "live"
    session = LiveSession(root, predictions="sim", out=out, guide=False)
    frames = ds.frames
    for f in frames[:3]:
        session.add_frame(f)
    before = (out / "live.jsonl").read_text()
    nan = np.full((4, 4), np.nan)
    up = session.add_frame(frames[3], nan)
    assert up.skipped and up.skipped[0][0] == frames[3] and "finite" in up.skipped[0][1]
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"not a png")
    up = session.add_frame(frames[4], ds.base_T_ee[frames[4]], images={"cam0": bad})
    assert up.skipped and str(bad) in up.skipped[0][1]
    up = session.add_frame("9999", np.eye(4))
    assert up.skipped and "9999" in up.skipped[0][1]
    assert up.ee_T_cam  # the last good state is carried
    up = session.add_frame(frames[5])
    assert not up.skipped and up.frames == frames[:3] + [frames[5]] and up.ee_T_cam
    assert (out / "live.jsonl").read_text().startswith(before)


def test_a_replay_names_a_pose_row_that_does_not_parse_once(simulated, tmp_path, caplog):
    """A robot_poses.csv row with a NaN is said once, as a warning naming its frame, and the replay goes
    on without that frame (it was left out silently before)."""
    import logging
    import shutil

    root = tmp_path / "ds"
    shutil.copytree(simulated(**SIM), root)
    rows = (root / "robot_poses.csv").read_text().splitlines()
    bad = rows[3].split(",")
    rows[3] = ",".join([bad[0], "nan", *bad[2:]])
    (root / "robot_poses.csv").write_text("\n".join(rows) + "\n")
    with caplog.at_level(logging.WARNING, logger="calib3r_graph"):
        session = LiveSession(root, predictions="sim", guide=False)
        ups = replay(session, "recorded")
    said = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and bad[0] in r.getMessage()]
    assert len(said) == 1 and "left out" in said[0]
    assert bad[0] not in ups[-1].frames and len(ups[-1].frames) == len(rows) - 2 and ups[-1].ee_T_cam


def test_guidance_stays_in_the_visited_region_and_looks_at_the_scene(simulated):
    from calib3r_graph.solver import guidance
    from calib3r_graph.solver.guidance import candidate_poses, scene_geometry

    root = simulated(**SIM)
    session = LiveSession(root, predictions="sim", k_next=5, margin_m=0.05)
    for f in load_dataset(root).frames[:5]:
        up = session.add_frame(f)
    assert len(up.next_poses) == 5
    visited = np.array([T.translation() for T in session.base_T_ee.values()])
    lo, hi = visited.min(0) - 0.05, visited.max(0) + 0.05
    X = session.sol.ee_T_cam["cam0"]
    centroid, dist = scene_geometry(session.sol)
    for T in up.next_poses:
        E = gtsam.Pose3(np.array(T))
        assert np.all(E.translation() >= lo - 1e-9) and np.all(E.translation() <= hi + 1e-9)
        C = E.compose(X)
        to_scene = centroid - C.translation()
        # at the distances seen so far, or (the scale moves, solver/guidance.py) within DISTANCE_STEPS of their median
        step = max(guidance.DISTANCE_STEPS)
        lo_d, hi_d = min(dist.min(), np.median(dist) * (1 - step)), max(dist.max(), np.median(dist) * (1 + step))
        assert lo_d * 0.99 <= np.linalg.norm(to_scene) <= hi_d * 1.01
    kinds = {k for k, _ in candidate_poses(session.sol, session.base_T_ee)}
    assert {"toward", "away", "rotate"} <= kinds or {"toward", "rotate"} <= kinds or {"away", "rotate"} <= kinds


@pytest.mark.parametrize("order", ["guided"])
def test_guided_replay_uses_each_frame_once(simulated, order):
    root = simulated(**SIM)
    session = LiveSession(root, predictions="sim")
    ups = replay(session, order)
    frames = ups[-1].frames
    assert sorted(frames) == sorted(load_dataset(root).frames) and len(set(frames)) == len(frames)


def test_a_rig_of_two_cameras_is_calibrated_live_and_ends_at_the_batch_solve(simulated):
    """A rigid rig: every update with a calibration has each camera's ee_T_cam, whose total sigma
    covers the simulated truth (3 sigma on every ee axis), the guidance proposes poses, and the
    replay ends at solve on the same frames and predictions."""
    from calib3r_graph.io.dataset import load_ground_truth

    root = simulated(seed=11, frames=8, cameras=2, matches_per_pair=200)
    ds = load_dataset(root)
    truth = load_ground_truth(root)["hand_eye"]
    preds = load_predictions(root, "sim", ds.cameras, set(ds.frames))
    ref = solve(ds, preds, SolveOptions(noise=NoiseOptions(pixel_sigma_px=preds.info["match_noise_px"]),
                                        progress=False))
    session = LiveSession(root, predictions="sim", target_mm=0.01, target_deg=0.001)  # never done: always guided
    ups = [u for u in replay(session, "guided") if u.ee_T_cam]
    assert len(ups) >= 6
    for u in ups:
        assert set(u.ee_T_cam) == {"cam0", "cam1"}
        for c, T in u.ee_T_cam.items():
            X = gtsam.Pose3(np.array(T))
            d = gtsam.Pose3.Logmap(truth[c].between(X))
            R = X.rotation().matrix()
            err = np.abs(np.r_[np.degrees(R @ d[:3]), 1e3 * (R @ d[3:])])
            s = u.sigma_ee_frame[c]
            sigma = np.array([s[k] for k in ("rx_deg", "ry_deg", "rz_deg", "x_mm", "y_mm", "z_mm")])
            assert np.all(err <= 3 * sigma), (len(u.frames), c, err / sigma)
    assert all(len(u.next_poses) > 0 for u in ups[:-1])
    for c, X in session.sol.ee_T_cam.items():
        assert np.all(np.abs(_z(X, ref.ee_T_cam[c], ref.covariance[c])) < 1e-6)


def test_watch_takes_complete_frames_names_a_bad_row_and_resumes(simulated, tmp_path):
    """--watch: frames whose pose row and predictions are there are added in the file's order, a NaN
    row is named and skipped; a second session with --resume continues from live.jsonl."""
    import shutil

    from calib3r_graph.live.run import watch

    root = tmp_path / "ds"
    shutil.copytree(simulated(**SIM), root)
    rows = (root / "robot_poses.csv").read_text().splitlines()
    (root / "robot_poses.csv").write_text("\n".join(rows[:4] + ["9998,nan,0,0,0,0,0,1"]) + "\n")
    out = tmp_path / "live"
    session = LiveSession(root, predictions="sim", out=out, guide=False)
    seen = []
    watch(session, poll_s=0.01, on_update=seen.append, max_idle_s=0.05)
    assert [len(u.frames) for u in seen] == [1, 2, 3, 3, 3]  # the last: solve on the 3 frames, at the idle end
    assert seen[-1].message.startswith("final: solve on all 3 frames") and "final" not in seen[-2].message
    assert seen[-2].skipped[0][0] == "9998" and "NaN" in seen[-2].skipped[0][1]
    full = load_dataset(simulated(**SIM))
    ds3 = subset_dataset(full, seen[-1].frames)
    preds3 = subset_predictions(load_predictions(full.root, "sim", full.cameras, set(full.frames)), seen[-1].frames)
    ref = solve(ds3, preds3, SolveOptions(noise=NoiseOptions(pixel_sigma_px=preds3.info["match_noise_px"]),
                                          progress=False))
    X = gtsam.Pose3(np.array(seen[-1].ee_T_cam["cam0"]))
    assert np.all(np.abs(_z(X, ref.ee_T_cam["cam0"], ref.covariance["cam0"])) < 1e-6)
    assert json.loads((out / "calibration.json").read_text())["cameras"]["cam0"]["T_ee_cam"] == seen[-1].ee_T_cam["cam0"]
    (root / "robot_poses.csv").write_text("\n".join(rows) + "\n")  # the rest arrives; a new session resumes
    again = LiveSession(root, predictions="sim", out=out, guide=False)
    more = []
    watch(again, poll_s=0.01, on_update=more.append, max_idle_s=0.05, resume=True)
    assert more[0].step == seen[-1].step + 1 and len(more[0].frames) == 3  # the killed session's frames, one solve
    assert more[-1].frames == [r.split(",")[0] for r in rows[1:]]
    steps = [json.loads(x)["step"] for x in (out / "live.jsonl").read_text().splitlines()]
    assert steps == list(range(1, len(steps) + 1))


def test_watch_proposes_the_next_poses_in_the_users_pose_format(simulated, tmp_path, capsys):
    """--watch --poses in a KUKA's format (x y z in mm, A B C in degrees, ee_T_base here): next_poses.csv
    and the printed proposals are in that format, unit and direction, and read back with the same
    reader they are the 4x4 base_T_ee of live.jsonl, so a user can hand them to the robot as they are."""
    import shutil

    from calib3r_graph.io.pose_files import parse_format, to_numbers
    from calib3r_graph.live.poses import PoseFiles

    root = tmp_path / "ds"
    shutil.copytree(simulated(**SIM), root)
    ds = load_dataset(root)
    fmt = parse_format("xyz-euler:zyx:deg")
    rows = []
    for f in ds.frames:  # as the controller writes them: the inverse pose, mm and degrees
        M = ds.base_T_ee[f].inverse().matrix()
        M[:3, 3] *= 1e3
        rows.append(f"{int(f)} " + " ".join(f"{v:.12g}" for v in to_numbers(M, fmt)))
    (root / "kuka.txt").write_text("\n".join(rows) + "\n")
    (root / "robot_poses.csv").unlink()
    out = tmp_path / "live"
    assert main(["-q", "live", str(root), "--watch", "--poses", str(root / "kuka.txt"), "--pose-format",
                 "xyz-euler:zyx:deg", "--unit", "mm", "--direction", "ee_T_base", "--out", str(out), "--next", "3",
                 "--poll-s", "0.01", "--idle-s", "0.2", "--target-mm", "0.001"]) == 0
    last = json.loads((out / "live.jsonl").read_text().splitlines()[-1])
    assert last["frames"] == ds.frames and len(last["next_poses"]) == 3
    csv = (out / "next_poses.csv").read_text().splitlines()
    assert csv[0] == "frame,x,y,z,a,b,c" and [r.split(",")[0] for r in csv[1:]] == ["next01", "next02", "next03"]
    (tmp_path / "next.txt").write_text("".join(" ".join(r.split(",")[1:]) + "\n" for r in csv[1:]))
    back = PoseFiles(str(tmp_path / "next.txt"), "xyz-euler:zyx:deg", unit="mm", direction="ee_T_base").poll()
    for (_, T, why), want in zip(back, last["next_poses"]):
        assert why is None
        np.testing.assert_allclose(T[:3, 3], np.asarray(want)[:3, 3], atol=1e-8)  # m
        np.testing.assert_allclose(T[:3, :3], np.asarray(want)[:3, :3], atol=1e-8)
    printed = capsys.readouterr().out
    assert "xyz-euler:zyx:deg, mm, ee_T_base" in printed and csv[1].split(",")[4] in printed


def test_a_watch_that_never_solved_does_not_claim_a_calibration(simulated, tmp_path, capsys):
    """Two poses cannot be solved: the end of the run names the files it wrote, not calibration.json."""
    import shutil

    root = tmp_path / "ds"
    shutil.copytree(simulated(**SIM), root)
    rows = (root / "robot_poses.csv").read_text().splitlines()
    (root / "robot_poses.csv").write_text("\n".join(rows[:3]) + "\n")
    out = tmp_path / "live"
    assert main(["-q", "live", str(root), "--watch", "--out", str(out), "--poll-s", "0.01", "--idle-s", "0.1"]) == 0
    assert not (out / "calibration.json").exists() and (out / "live.jsonl").is_file()
    assert f"wrote {out}/next_poses.csv, live.jsonl (no calibration.json" in capsys.readouterr().out


@pytest.mark.parametrize("kind", ["robot_poses.csv", "one pose file"])
def test_watch_waits_for_the_line_end_of_a_last_pose_row(tmp_path, kind):
    """A capture script's row caught mid-write can cut its last number and still parse (an angle of
    -178.5 cut to -17): a last line without its line end is read only once the file has not changed
    over two polls, so a row completed in between is read whole; one left so is read as it stands, a
    poll later."""
    import os

    from calib3r_graph.live.poses import PoseFiles, RobotPosesCsv

    f = tmp_path / ("robot_poses.csv" if kind == "robot_poses.csv" else "poses.txt")
    head = "frame,x,y,z,qx,qy,qz,qw\n" if kind == "robot_poses.csv" else ""
    first = "0001,0.5,0.2,0.3,0,0,0,1\n" if kind == "robot_poses.csv" else "1 0.5 0.2 0.3 0 0 0 1\n"
    whole = "0002,0.1234,0.2,0.3,0,0,0,1\n" if kind == "robot_poses.csv" else "2 0.1234 0.2 0.3 0 0 0 1\n"
    poses = RobotPosesCsv(f, "m") if kind == "robot_poses.csv" else PoseFiles(str(f), pose_format="xyz-quat-xyzw")
    f.write_text(head + first + whole[:-1])  # the second row all there but its line end
    assert [r[0] for r in poses.poll()] == ["0001"]
    f.write_text(head + first + whole)  # the line end arrives: read whole
    os.utime(f, ns=(1, 2))
    rows = poses.poll()
    assert [r[0] for r in rows] == ["0001", "0002"] and abs(rows[1][1][0, 3] - 0.1234) < 1e-12
    # left without its line end: held back at first, then read as it stands (the file settled)
    cut = "0003,0.1,0.2,0.3,0,0,0,1" if kind == "robot_poses.csv" else "3 0.1 0.2 0.3 0 0 0 1"
    f.write_text(head + first + whole + cut)
    assert [r[0] for r in poses.poll()] == ["0001", "0002"]
    assert [r[0] for r in poses.poll()] == ["0001", "0002", "0003"]


def test_watch_reads_per_frame_json_poses_as_import_files_does(simulated, tmp_path):
    """--watch --poses DIR --pose-key: a capture script writes each frame as an image and a JSON pose
    file (Franka-like: a column-major O_T_EE under a nested key); watch reads them with import files'
    readers and the pairwise frontend runs on the images. A half-written JSON waits for the rest; a NaN
    pose and an unreadable image are named and skipped; the session goes on."""
    import shutil
    import threading
    import time

    from calib3r_graph.live.poses import PoseFiles
    from calib3r_graph.live.run import watch

    src = simulated(seed=3, frames=6, images=True, width=320, height=240)
    ds = load_dataset(src)
    root = tmp_path / "ds"
    (root / "images" / "cam0").mkdir(parents=True)
    (root / "poses").mkdir()
    shutil.copy(src / "dataset.yaml", root)  # the cameras only: no robot_poses.csv, no predictions
    poses = PoseFiles(str(root / "poses"), pose_key="robot.O_T_EE")

    def pose_json(M):
        return json.dumps({"robot": {"O_T_EE": np.asarray(M).T.ravel().tolist(), "q": [0.0] * 7}})

    # a file the script is still writing is not named yet; once whole, it is read
    (root / "poses" / "pose_0.json").write_text(pose_json(ds.base_T_ee["0000"].matrix())[:25])
    assert poses.poll() == []
    (root / "poses" / "pose_0.json").write_text(pose_json(ds.base_T_ee["0000"].matrix()))
    (frame, T, reason), = poses.poll()
    assert frame == "0000" and reason is None and np.allclose(T, ds.base_T_ee["0000"].matrix())
    (root / "poses" / "pose_0.json").unlink()

    def capture():  # image first, then its pose, each by rename (what a capture script should do)
        for i, f in enumerate(ds.frames):
            img = root / "images" / "cam0" / f"{f}.png"
            tmp = img.with_suffix(".tmp")
            if i == 4:
                tmp.write_bytes(b"not a png")
            else:
                shutil.copy(ds.image_path("cam0", f), tmp)
            tmp.rename(img)
            M = ds.base_T_ee[f].matrix()
            if i == 3:
                M[0, 3] = np.nan
            tmp = root / "poses" / "pose.tmp"
            tmp.write_text(pose_json(M))
            tmp.rename(root / "poses" / f"pose_{i}.json")
            time.sleep(0.05)

    thread = threading.Thread(target=capture)
    thread.start()
    session = LiveSession(root, target_mm=0.01, target_deg=0.001, out=tmp_path / "live", guide=False)
    seen = []
    watch(session, poll_s=0.02, on_update=seen.append, max_idle_s=3.0, poses=poses)
    thread.join()
    skipped = {f: r for u in seen for f, r in u.skipped}
    assert set(skipped) == {"0003", "0004"}
    assert "pose_3.json" in skipped["0003"] and "NaN" in skipped["0003"]
    assert "0004.png" in skipped["0004"] and "cannot read" in skipped["0004"]
    assert seen[-1].frames == ["0000", "0001", "0002", "0005"] and seen[-1].ee_T_cam
    # the poses were read right (column-major, metres, base_T_ee): the hand-eye is the simulated one
    import yaml

    from calib3r_graph.geometry import pose_error

    h = yaml.safe_load((src / "ground_truth.yaml").read_text())["hand_eye"]["cam0"]
    truth = gtsam.Pose3(gtsam.Rot3.Quaternion(h["qw"], h["qx"], h["qy"], h["qz"]), np.array([h["x"], h["y"], h["z"]]))
    t_err, r_err = pose_error(gtsam.Pose3(np.array(seen[-1].ee_T_cam["cam0"])), truth)
    assert t_err < 0.01 and r_err < 1.0, (t_err, r_err)  # 4 poses of 320x240 images: mm, not a wrong convention
    lines = (tmp_path / "live" / "live.jsonl").read_text().splitlines()
    assert len(lines) == len(seen) and json.loads(lines[-1])["frames"] == seen[-1].frames


def test_live_pairing_picks_each_new_views_best_partners_and_ends_at_the_batch_solve(simulated, tmp_path):
    """The pairwise frontend run live pairs a new view with its `partners` best earlier views (the
    batch frontend's pair selection: its own picks, the earlier views that pick it, then at most
    `partners` a round for its `more_rounds`), not with every earlier view; the last replay step is
    still the batch frontend and solve."""
    from calib3r_graph.frontends.pairwise import PairwiseOptions, pairwise_predictions

    root = simulated(seed=3, frames=8, images=True, width=320, height=240)
    opt = PairwiseOptions(partners=2, more_rounds=1)
    session = LiveSession(root, out=tmp_path / "live", guide=False)
    session.source.opt = opt
    ups = replay(session, "random", seed=2)
    src = session.source
    n = len(src.feats)
    assert n == 8 and len(src.picked) == n
    for k, f in enumerate(session.base_T_ee):  # arrival order
        own, _, *more = src.picked[f"cam0/{f}"]
        assert len(own) == min(opt.partners, k)  # its best partners among the k earlier views
        assert len(more) <= opt.more_rounds and all(len(r) <= opt.partners for r in more), more
    assert len(src.geoms) < n * (n - 1) // 2  # not every pair was matched
    ds = load_dataset(root)
    preds = pairwise_predictions(ds, None, opt, tmp_path / "live" / "cache", progress=False)
    ref = solve(ds, preds, SolveOptions(noise=NoiseOptions(pixel_sigma_px=preds.info["match_noise_px"]),
                                        progress=False))
    assert ups[-1].ee_T_cam
    for c, X in session.sol.ee_T_cam.items():
        assert np.all(np.abs(_z(X, ref.ee_T_cam[c], ref.covariance[c])) < 1e-6)


def test_a_view_whose_pairs_are_all_cut_leaves_the_update_not_the_session(simulated, monkeypatch):
    """A view that no pair with three weighted matches determines (the re-weighting cut all of its
    pairs) would leave the information singular: as in ``solve`` it leaves that update
    (update.UpdateContext.drop_weak), is named in views_dropped, and the calibration goes on."""
    from calib3r_graph.live import update as live_update

    root = simulated(seed=7, frames=12, cameras=1, matches_per_pair=200)
    weak = "cam0/0004"
    real = live_update.robust_weights

    def cut(observations, residuals, whitening, conf, **kw):  # the real weights, the weak view's pairs cut
        w = real(observations, residuals, whitening, conf, **kw)
        return [x * 0 if weak in (o.view_a, o.view_b) else x for o, x in zip(observations, w)]

    monkeypatch.setattr(live_update, "robust_weights", cut)  # (every update's weights: UpdateContext.irls_weights)
    session = LiveSession(root, predictions="sim", guide=False)
    ups = [session.add_frame(f) for f in session.poses_known]
    # before: from the first calibration on, every update with the view failed as singular
    first = next(i for i, u in enumerate(ups) if u.ee_T_cam)
    assert first <= 6 and all(u.ee_T_cam and "not observable" not in u.message for u in ups[first:]), \
        [u.message for u in ups]
    assert weak in {d["view"] for d in session.sol.views_dropped}
    assert weak not in session.sol.base_T_cam and len(session.sol.base_T_cam) == len(ups) - 1


def test_the_readmes_capture_loop_runs_as_written(simulated, tmp_path, monkeypatch, capsys):
    """README's LiveSession example, executed as it stands but for a target no 8 frames reach (the
    simulator's is met at 3), on a simulated cell: images handed as HxWx3 uint8 arrays, no move
    before the first calibration, the robot moved to each later update's first proposal, the
    session finished. If the API the README shows changes, this fails (it did: the example moved the
    robot to ``next_poses[0]`` before there was one)."""
    import re
    import shutil
    from pathlib import Path

    import cv2

    root = simulated(seed=3, frames=8, images=True, width=320, height=240)
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    code = next(b for b in re.findall(r"```python\n(.*?)```", readme, re.S) if "LiveSession(" in b)
    assert "target_mm=1.0, target_deg=0.1" in code
    code = code.replace("target_mm=1.0, target_deg=0.1", "target_mm=0.001, target_deg=0.0001")
    (tmp_path / "mycell").mkdir()
    shutil.copy(root / "dataset.yaml", tmp_path / "mycell" / "dataset.yaml")  # the cameras only
    monkeypatch.chdir(tmp_path)
    ds = load_dataset(root)
    moved = []

    def capture():
        for f in ds.frames:
            image = cv2.imread(str(root / "images" / "cam0" / f"{f}.png"))[:, :, ::-1].copy()
            yield f, ds.base_T_ee[f].matrix(), image

    class Robot:
        def move_to(self, base_T_ee):
            moved.append(np.asarray(base_T_ee))

    scope = {"capture": capture, "robot": Robot()}
    exec(compile(code, "README.md", "exec"), scope)
    final = scope["final"]
    assert set(final.ee_T_cam) == {"cam0"} and np.all(np.isfinite(np.asarray(final.ee_T_cam["cam0"])))
    lines = [x for x in capsys.readouterr().out.splitlines() if x.strip()]
    assert len(lines) == 8 and all("frames" in x for x in lines)  # a status line a frame
    waiting = sum("waiting" in x for x in lines)
    assert 1 <= waiting <= 3 and len(moved) == 8 - waiting  # a move after every calibrated update
    assert all(M.shape == (4, 4) and np.allclose(M[3], [0, 0, 0, 1]) for M in moved)
    assert (tmp_path / "mycell_live" / "calibration.json").is_file()
