"""Live guidance (solver/plan.py): on an orbit, where the metric scale cannot be observed, the guide
proposes a move toward or away from the scene first, and the pose it proposes, rendered and added,
measures the scale. Fixed replay orders (live/run.py's replay with a list)."""

import gtsam
import numpy as np
import pytest

from calib3r_graph.io.dataset import load_dataset
from calib3r_graph.live import LiveSession
from calib3r_graph.live.run import replay
from calib3r_graph.simulate import render_poses

# An orbit like rwhe_kuka_2's (simulate.orbit_trajectory), small images: the pairwise RGB frontend on
# them. The targets are tight so that the session keeps proposing poses.
ORBIT = dict(seed=0, frames=6, trajectory="orbit", width=320, height=240, matches_per_pair=200,
             prediction_downsample=4, images=True)


def _scale_rel(up) -> float:
    lam, sigma = up.metric_scale["cam0"]
    return sigma / abs(lam)


def test_orbit_guidance_moves_toward_or_away_first_and_measures_the_scale(simulated, tmp_path):
    from calib3r_graph.solver.plan import distance_band, scene_geometry

    root = simulated(**ORBIT)
    session = LiveSession(root, target_mm=0.5, target_deg=0.05, out=tmp_path / "live")
    frames = list(session.poses_known)
    for i, f in enumerate(frames):
        session.guide = i == len(frames) - 1  # proposals for the last orbit frame only (the test's time)
        up = session.add_frame(f, images={"cam0": str(root / "images" / "cam0" / f"{f}.png")})
    assert up.metric_scale and up.next_poses, up.message
    # the orbit: every camera at one distance (within 3 %), so the scale is weak
    _, dist = scene_geometry(session.sol)
    assert dist.max() / dist.min() < 1.1
    before = _scale_rel(up)
    assert before > 0.01, f"the orbit alone measures the scale to {before:.2%}: not the weak case this tests"
    assert up.next_kinds[0] in ("toward", "away"), up.next_kinds
    lo, hi = distance_band(dist)
    centroid, _ = scene_geometry(session.sol)
    X = session.sol.ee_T_cam["cam0"]
    E = gtsam.Pose3(np.array(up.next_poses[0]))
    d_new = np.linalg.norm(E.compose(X).translation() - centroid)
    assert lo - 1e-6 <= d_new <= hi + 1e-6 and abs(d_new / np.median(dist) - 1) >= 0.09
    up = session.add_frame("guided1", E, images=render_poses(root, {"g": E})["g"])
    assert "cam0/guided1" in session.sol.base_T_cam, up.message
    after = _scale_rel(up)
    assert after < before / 3, f"scale sigma {before:.2%} -> {after:.2%}"


@pytest.mark.parametrize("cut", [4])
def test_replay_takes_a_fixed_order(simulated, cut):
    root = simulated(seed=5, frames=6, cameras=1, matches_per_pair=300)
    frames = load_dataset(root).frames
    order = frames[::-1][:cut]
    session = LiveSession(root, predictions="sim", guide=False)
    ups = replay(session, order)
    assert list(session.base_T_ee) == order and sorted(ups[-1].frames) == sorted(order) and ups[-1].ee_T_cam
    with pytest.raises(Exception, match="fixed order"):
        replay(LiveSession(root, predictions="sim", guide=False), order + ["nope"])
