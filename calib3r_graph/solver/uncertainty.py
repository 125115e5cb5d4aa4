"""How far to trust a calibration: noise calibration of the scene factors and
observability diagnostics.

Dense matches from a network are not independent: its depth errors are smooth, so
neighbouring matches share most of their error, and treating thousands of them as
independent makes the marginals over-confident by large factors. After the robust
rounds the solver calibrates the scene factors' noise from their own residuals:

* **A posteriori variance factor** ``sigma0^2``: the mean whitened residual per degree
  of freedom under the nominal per-point model (pixel + relative depth noise).
* **Effective number of independent observations** through Kish's design effect
  ``kappa``: matches are grouped in cells of the first view's image; if their errors
  were independent the squared norm of a cell's mean residual would be
  ``3 sigma0^2 / n_cell``; ``kappa = n_cell |mean|^2 / (3 sigma0^2)``, averaged over
  cells, measures how many matches count as one (``n_eff = n / kappa``).

The scene information is multiplied by ``1 / (sigma0^2 kappa)`` and the graph is
solved once more, so robot and scene factors are weighted by their real
(correlation-aware) noise and the marginals account for it.
"""

import numpy as np

from calib3r_graph.io.predictions import split_view_id

# Below this many robot poses the total sigma is not checked by the leave-one-pose-out jackknife
# (solver/jackknife.py): with 3 poses no pose can be left out (two poses do not solve), with 4 the
# jackknife has four samples, which span three of the six directions of ee_T_cam; and the robot's
# error field needs 8. Measured (bench/views_real.py --views 3,4,5 --repeats 20,
# bench/results/views_real_3to5.md): the share of seeded subsets whose error to the full recording's
# result is within 3 total sigma on every ee axis was 33 %, 67 % and 50 % at 3 poses on rwhe_kuka_1,
# rwhe_kuka_2 and tabb_ds1; 75 %, 89 %, 89 % at 4; 89 %, 100 %, 100 % at 5 (95 % on rwhe_kuka_2 under
# GTSAM's default LM damping bound, before solve.LM_LAMBDA_UPPER). The live replays
# (bench/live_real.py) gave the same picture per update: 48-58 % at 3 poses, 57-87 % at 4, 88-100 %
# from 5. So below it the summary says the sigma is unchecked, and `live` never says "done".
MIN_CHECKED_POSES = 5


def noise_calibration(observations, residuals, unit_sqrt_info, weights, grid_size, cells=(6, 8), whitened=None):
    """(sigma0^2, kappa) of the scene factors from residuals at the solution.

    residuals: per pair (N, 3) unwhitened; unit_sqrt_info: per pair (N, 3, 3) nominal
    whitening; weights: per pair (N,) confidence x robust weight (0 = not used);
    grid_size: view -> (width, height) of the frontend grid; whitened: per pair ``W e`` (N, 3)
    if the caller has it already (the live engine).
    """
    if not observations:
        return 0.0, 1.0
    # All pairs at once: their matches concatenated, each match's cell numbered within its pair's
    # (the sums per cell are those of the pairs one by one, in the same order)
    w = np.concatenate(weights)
    if whitened is None:
        white = np.einsum("nij,nj->ni", np.concatenate(unit_sqrt_info), np.concatenate(residuals))
    else:
        white = np.concatenate(whitened)
    white = white * np.sqrt(w)[:, None]  # (as solve.robust_weights whitens)
    used = w > 0
    rows = 3 * int(used.sum())
    sigma0_sq = float((white[used] ** 2).sum() / max(rows, 1))
    n_cells = cells[0] * cells[1]
    counts = [len(o.uv_a) for o in observations]
    uv = np.concatenate([o.uv_a for o in observations])
    size = np.repeat(np.array([grid_size[o.view_a] for o in observations], float), counts, axis=0)
    cx = np.clip((uv[:, 0] / size[:, 0] * cells[1]).astype(int), 0, cells[1] - 1)
    cy = np.clip((uv[:, 1] / size[:, 1] * cells[0]).astype(int), 0, cells[0] - 1)
    cell = cy * cells[1] + cx + np.repeat(np.arange(len(observations)) * n_cells, counts)
    cell, r = cell[used], white[used]
    n_c = np.bincount(cell, minlength=len(observations) * n_cells)
    sums = np.stack([np.bincount(cell, weights=r[:, k], minlength=len(n_c)) for k in range(3)], 1)
    ok = n_c >= 5
    # n_c |mean|^2 = |sum|^2 / n_c; expected 3 sigma0^2 for independent errors
    num = float(((sums[ok] ** 2).sum(1) / n_c[ok]).sum())
    den = int(ok.sum())
    kappa = max(1.0, num / max(den, 1) / (3 * sigma0_sq)) if den else 1.0
    return sigma0_sq, kappa


def _direction(d) -> str:
    d = np.round(np.asarray(d, float) * np.sign(d[np.argmax(np.abs(d))]), 2) + 0.0  # + 0.0: no "-0.00"
    return f"[{d[0]:.2f} {d[1]:.2f} {d[2]:.2f}]"


MIN_ROTATION_DEG = 2.0  # below this between every two poses, the robot "did not rotate"
MIN_MOVE_MM = 1.0  # ... and with less translation than this, it "did not move"


def relative_rotations(base_T_ee: dict, frames) -> np.ndarray:
    """Rotation vectors Log(R_a^T R_b) (rad, in pose a's ee frame) of the flange between every two
    frames a < b in the given order, (P, 3), as ``np.triu_indices`` orders the pairs."""
    import gtsam

    R = np.array([base_T_ee[f].rotation().matrix() for f in frames]).reshape(-1, 3, 3)
    iu, ju = np.triu_indices(len(R), 1)
    rel = np.einsum("pji,pjk->pik", R[iu], R[ju])  # R_a^T R_b
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    angle = np.arccos(cos)
    vee = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], 1)
    sin = np.sin(angle)
    factor = np.where(sin > 1e-9, angle / (2 * np.where(sin > 1e-9, sin, 1.0)), 0.5)
    w = vee * factor[:, None]
    for k in np.flatnonzero(angle > np.pi - 1e-3):  # near a half turn the closed form loses the axis
        w[k] = gtsam.Rot3.Logmap(gtsam.Rot3(rel[k]))
    return w


def check_motion(base_T_ee: dict, frames, robot_file="robot_poses.csv"):
    """Before initialising: a robot that did not move, or only translated, cannot calibrate a
    hand-eye transform. Raises SolveError saying which, how much the poses rotate about which
    ee axes, and what to record instead."""
    from calib3r_graph.errors import SolveError

    frames = sorted(f for f in frames if f in base_T_ee)
    if len(frames) < 2:
        return
    w = relative_rotations(base_T_ee, frames)
    max_deg = float(np.degrees(np.linalg.norm(w, axis=1).max()))
    if max_deg >= MIN_ROTATION_DEG:
        return
    per_axis = np.degrees(np.abs(w).max(axis=0))
    t = np.array([base_T_ee[f].translation() for f in frames])
    move_mm = float(np.linalg.norm(t[:, None] - t[None], axis=2).max() * 1e3)
    rotation = (f"the flange rotates at most {max_deg:.2f} deg between any two poses "
                f"(about ee x {per_axis[0]:.2f}, y {per_axis[1]:.2f}, z {per_axis[2]:.2f} deg)")
    advice = ("record 8-10 poses that each rotate the flange 30-90 degrees from the others about at least two "
              "different axes (e.g. tilt and roll the tool), keeping the scene in view")
    if move_mm < MIN_MOVE_MM:
        raise SolveError(f"{robot_file}: the robot did not move: all {len(frames)} poses are the same (within "
                         f"{move_mm:.2f} mm; {rotation}); {advice}")
    raise SolveError(f"{robot_file}: the robot did not rotate: the poses differ by translations only (up to "
                     f"{move_mm:.0f} mm) and {rotation}; hand-eye calibration needs rotation: {advice}")


def motion_diagnostics(base_T_ee: dict, frames) -> list:
    """Plain-words warnings about the robot motion (too few poses, too little or degenerate rotation)."""
    frames = sorted(frames)
    msgs = []
    if len(frames) < MIN_CHECKED_POSES:
        checked = ("no pose can be left out to test it" if len(frames) < 4 else
                   "only a leave-one-pose-out of 4 poses tests it")
        outside = "33-67 %" if len(frames) < 4 else "11-43 %"
        msgs.append(f"only {len(frames)} robot poses: the sigma is not checked ({checked}; on real recordings "
                    f"the error was outside 3 sigma in {outside} of {len(frames)}-pose calibrations); use at least "
                    "8-10 poses for a reliable calibration")
    w = relative_rotations(base_T_ee, frames)
    angles = list(np.linalg.norm(w, axis=1))
    axes = [x for x, a in zip(w, angles) if a > np.radians(2)]  # angle-weighted axes
    rotation_warned = not angles or np.degrees(max(angles)) < 10
    if rotation_warned:
        msgs.append("the flange rotates less than 10 degrees between any two poses: the translation of ee_T_cam "
                    "is poorly constrained; add poses rotated 30-90 degrees about different axes")
    elif len(axes) >= 2:
        # Second singular value of the (angle-weighted) rotation axes: ~0 when all axes are parallel.
        _, s, Vt = np.linalg.svd(np.array(axes), full_matrices=False)
        rotation_warned = s[1] < 0.15 * s[0]
        if rotation_warned:
            msgs.append(f"all robot rotations are about nearly parallel axes (ee axis ~{_direction(Vt[0])}): "
                        f"the translation of ee_T_cam along that axis is poorly constrained; add "
                        "poses that rotate about a perpendicular axis")
    if not rotation_warned:  # otherwise the warning above already says the rotations are poor
        gain, axis = systematic_error_gain(base_T_ee, frames)
        if gain > 5.0:
            msgs.append(f"the flange rotates little about the axes perpendicular to ee direction {_direction(axis)}: "
                        f"each mm of systematic error in the robot's or the camera's relative translations moves "
                        f"the translation of ee_T_cam along it by about {gain:.0f} mm, which no sigma shows; add "
                        "poses that rotate 20-40 degrees about axes perpendicular to it")
    pure = np.mean(np.degrees(angles) < 1.0) if angles else 0.0
    if pure > 0.5:
        msgs.append(f"{100 * pure:.0f} % of pose pairs are pure translations: they fix the scale and rotation but "
                    "not the translation of ee_T_cam; add rotated poses")
    return msgs


def systematic_error_gain(base_T_ee: dict, frames) -> tuple[float, np.ndarray]:
    """How much a systematic (not averaging out) error in relative translations moves t of ee_T_cam.

    AX = XB's translation part, (R_A - I) t_X = R_X t_B - t_A over all pose pairs, fixes t_X
    only through the flange's rotations: along an ee direction that the rotations barely move
    (rms of |(R_A - I) d| small), a bias of 1 mm in the robot's or the camera's relative
    translations becomes 1 / rms mm in t_X. Returns (largest such gain, its ee direction).
    The sum over pairs needs no loop: sum_{a<b} (R_ab - I)^T (R_ab - I) = 2 P I - (G^T G - n I)
    with R_ab = R_a^T R_b, G = sum_a R_a and P = n (n - 1) / 2 pairs.
    """
    R = np.array([base_T_ee[f].rotation().matrix() for f in frames])
    n = len(R)
    pairs = n * (n - 1) / 2
    if pairs < 1:
        return float("inf"), np.array([0.0, 0.0, 1.0])
    G = R.sum(axis=0)
    S = (2 * pairs + n) * np.eye(3) - G.T @ G
    lam, V = np.linalg.eigh((S + S.T) / (2 * pairs))
    return float(1 / np.sqrt(max(lam[0], 1e-12))), V[:, 0]


def covariance_diagnostics(camera: str, T_ee_cam, cov, weak_mm: float = 2.0, weak_deg: float = 0.2) -> list:
    """Warnings for poorly constrained directions of ee_T_cam, read off its marginal covariance."""
    from calib3r_graph.io.results import covariance_in_ee_frame

    C = covariance_in_ee_frame(T_ee_cam, cov)
    msgs = []
    for block, unit, scale, limit, what in ((slice(3, 6), "mm", 1e3, weak_mm, "translation"),
                                            (slice(0, 3), "deg", np.degrees(1), weak_deg, "rotation")):
        lam, V = np.linalg.eigh(C[block, block])
        sigma = np.sqrt(max(lam[-1], 0)) * scale
        if sigma > limit:
            hint = ("add poses that rotate the flange about axes perpendicular to this direction"
                    if what == "translation" else "add poses that rotate about this axis and other axes")
            msgs.append(f"{camera}: {what} along ee direction {_direction(V[:, -1])} is poorly "
                        f"constrained (sigma {sigma:.2f} {unit}); {hint}")
    return msgs


def views_by_camera(views) -> dict:
    out = {}
    for v in views:
        out.setdefault(split_view_id(v)[0], []).append(v)
    return out
