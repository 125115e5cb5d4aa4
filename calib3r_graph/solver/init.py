"""Initialisation from the data alone: no ground truth, no nominal mount.

1. Every view pair: a robust Sim(3) between the two views' back-projected matches
   (RANSAC + Umeyama) -> relative pose and relative depth scale, plus inlier masks.
2. Per connected component of the co-visibility graph, a maximum spanning tree
   (weighted by inlier count) chains them into visual poses and depth scales in the
   root view's units.
3. Closed-form hand-eye with scale: rotations by Wahba/Kabsch on the rotation axes of
   AX = XB over all motion pairs of each camera; then one linear least-squares solve
   for every camera's translation and every component's metric scale
   ``(R_A - I) t_X - lambda R_X t_B = -t_A``.
4. Each component is moved into the robot base frame (mean of ``base_T_ee X (visual pose)^-1``),
   and depth scales become metres per frontend unit.
"""

import logging
from dataclasses import dataclass, field

import gtsam
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree

from calib3r_graph.errors import InputError, SolveError
from calib3r_graph.geometry import hand_eye_rotation, mean_pose, project_to_so3, ransac_sim3
from calib3r_graph.io.predictions import split_view_id

log = logging.getLogger(__name__)

# Pure translations enter the hand-eye rotation as unit directions at the weight of a 0.1 rad
# rotation axis: they determine R_X about an axis that the rotations leave free and hardly move it
# where the rotations determine it (the solve refines it either way).
TRANSLATION_WEIGHT = 0.1

MIN_INLIERS = 15


@dataclass
class Initialisation:
    base_T_cam: dict  # view id -> Pose3 (metres, base frame)
    depth_scale: dict  # view id -> metres per frontend depth unit
    ee_T_cam: dict  # camera -> Pose3
    components: list  # [[view id, ...], ...]
    inliers: list  # per observation pair: bool mask (or None for a dropped pair)
    dropped_views: list = field(default_factory=list)  # [{"view", "reason"}]


def pairwise_sim3(observations, rel_threshold=0.03, seed=0):
    """[(s_ab, R_ab, t_ab, inliers) or None] with P_a ~ s_ab R_ab P_b + t_ab (view a's units)."""
    rng = np.random.default_rng(seed)
    out = []
    for o in observations:
        r = ransac_sim3(o.pts_b, o.pts_a, rel_threshold, rng=rng) if len(o) >= MIN_INLIERS else None
        out.append(r if r is not None and r[3].sum() >= MIN_INLIERS else None)
    return out


def spanning_tree_poses(views, observations, sims):
    """Per component: {view: (world_T_cam Pose3 in root units, depth scale)}."""
    index = {v: i for i, v in enumerate(views)}
    rows, cols, weights, edge_of = [], [], [], {}
    for k, (o, sim) in enumerate(zip(observations, sims)):
        if sim is None:
            continue
        a, b = index[o.view_a], index[o.view_b]
        rows.append(a)
        cols.append(b)
        weights.append(1.0 / (1.0 + sim[3].sum()))  # minimum spanning tree of 1/inliers
        edge_of[(a, b)] = (k, False)
        edge_of[(b, a)] = (k, True)
    n = len(views)
    G = coo_matrix((weights, (rows, cols)), shape=(n, n)).tocsr()
    n_comp, labels = connected_components(G, directed=False)
    T = minimum_spanning_tree(G)
    T = T + T.T
    comps = []
    for c in range(n_comp):
        members = np.flatnonzero(labels == c)
        degree = np.asarray((G + G.T)[members].getnnz(axis=1))
        root = members[np.argmax(degree)]
        order, pred = breadth_first_order(T, root, directed=False)
        poses = {views[root]: (gtsam.Pose3(), 1.0)}
        for i in order[1:]:
            p = pred[i]
            k, flipped = edge_of[(p, i)]
            s, R, t, _ = sims[k]
            if flipped:  # the edge is stored as (i, p): invert P_i = s R P_p + t
                R, s = R.T, 1.0 / s
                t = -s * R @ t
            # Edge maps child points to parent: P_p = s R P_i + t.
            T_p, s_p = poses[views[p]]
            R_i = T_p.rotation().matrix() @ R
            t_i = T_p.translation() + s_p * T_p.rotation().matrix() @ t
            poses[views[i]] = (gtsam.Pose3(gtsam.Rot3(project_to_so3(R_i)), t_i), s_p * s)
        comps.append(poses)
    return comps


def _motion_pairs(comp_views, max_pairs, rng):
    """All pairs of views of the same camera in one component (random subset if many)."""
    by_cam = {}
    for v in comp_views:
        by_cam.setdefault(split_view_id(v)[0], []).append(v)
    pairs = [(a, b) for vs in by_cam.values() for i, a in enumerate(vs) for b in vs[i + 1:]]
    if len(pairs) > max_pairs:
        pairs = [pairs[i] for i in rng.choice(len(pairs), max_pairs, replace=False)]
    return pairs


def hand_eye_closed_form(comps, base_T_ee, robot_file="robot_poses.csv", max_pairs=4000, seed=0):
    """Every camera's ee_T_cam and every component's metric scale (metres per visual unit)."""
    rng = np.random.default_rng(seed)
    comp_pairs = [_motion_pairs(list(c), max_pairs, rng) for c in comps]
    frame = lambda v: split_view_id(v)[1]
    cameras = sorted({split_view_id(v)[0] for c in comps for v in c})
    R_X = {}
    for cam in cameras:
        alphas, alphas_inv, betas, dirs_a, dirs_b = [], [], [], [], []
        for c, pairs in zip(comps, comp_pairs):
            for a, b in pairs:
                if split_view_id(a)[0] != cam:
                    continue
                E1, E2 = base_T_ee[frame(a)], base_T_ee[frame(b)]
                B = c[a][0].between(c[b][0])
                beta = gtsam.Rot3.Logmap(B.rotation())
                if np.linalg.norm(beta) < np.radians(1.0):
                    # A pure translation has no axis, but t_A = s R_X t_B: its direction constrains R_X
                    # (what a single rotation axis leaves free, e.g. once the frontend drops a view).
                    A = E1.between(E2)
                    t_a, t_b = A.translation(), B.translation()
                    if (np.linalg.norm(gtsam.Rot3.Logmap(A.rotation())) < np.radians(1.0)
                            and np.linalg.norm(t_a) > 0 and np.linalg.norm(t_b) > 0):
                        dirs_a.append(t_a / np.linalg.norm(t_a))
                        dirs_b.append(t_b / np.linalg.norm(t_b))
                    continue
                alphas.append(gtsam.Rot3.Logmap(E1.between(E2).rotation()))
                alphas_inv.append(gtsam.Rot3.Logmap(E1.compose(E2.inverse()).rotation()))
                betas.append(beta)
        if len(betas) < 1 or len(betas) + len(dirs_a) < 2:
            raise SolveError(f"camera {cam}: fewer than two robot motions with rotation between co-visible "
                             "views; add poses that rotate the flange about different axes")
        alphas, alphas_inv, betas = map(np.array, (alphas, alphas_inv, betas))
        R, res = hand_eye_rotation(alphas, betas)
        _, res_inv = hand_eye_rotation(alphas_inv, betas)
        if dirs_a:
            R, _ = hand_eye_rotation(np.vstack([alphas, TRANSLATION_WEIGHT * np.array(dirs_a)]),
                                     np.vstack([betas, TRANSLATION_WEIGHT * np.array(dirs_b)]))
        log.info("camera %s: hand-eye rotation from %d motions, axis residual %.3f deg (inverted poses: %.3f deg)",
                 cam, len(betas), res, res_inv)
        if res > 1.0 and res_inv < 0.3 * res:
            raise InputError(robot_file, f"robot poses look inverted (ee_T_base given as base_T_ee): the "
                                         f"visual motion fits the inverse with {res_inv:.2f} deg axis error "
                                         f"against {res:.2f} deg; invert the poses")
        R_X[cam] = R
    # Translations and scales: one linear system.
    n_cam, n_comp = len(cameras), len(comps)
    A_rows, b_rows = [], []
    for ci, (c, pairs) in enumerate(zip(comps, comp_pairs)):
        for a, b in pairs:
            j = cameras.index(split_view_id(a)[0])
            A = base_T_ee[frame(a)].between(base_T_ee[frame(b)])
            B = c[a][0].between(c[b][0])
            row = np.zeros((3, 3 * n_cam + n_comp))
            row[:, 3 * j:3 * j + 3] = A.rotation().matrix() - np.eye(3)
            row[:, 3 * n_cam + ci] = -R_X[cameras[j]] @ B.translation()
            A_rows.append(row)
            b_rows.append(-A.translation())
    if not A_rows:
        raise SolveError("no robot motion between co-visible views: nothing constrains the hand-eye transform")
    sol, *_ = np.linalg.lstsq(np.vstack(A_rows), np.concatenate(b_rows), rcond=None)
    scales = sol[3 * n_cam:]
    ee_T_cam = {cam: gtsam.Pose3(gtsam.Rot3(R_X[cam]), sol[3 * j:3 * j + 3]) for j, cam in enumerate(cameras)}
    return ee_T_cam, scales


def initialise(views, observations, base_T_ee, robot_file="robot_poses.csv", visual_poses=None,
               seed=0) -> Initialisation:
    """``visual_poses`` ({view: world_T_cam 4x4}, e.g. COLMAP's, in the predictions' depth unit)
    replaces the spanning tree of pairwise alignments when given. ``seed``: the pairwise RANSAC's and
    the closed form's random draws (``SolveOptions.seed``)."""
    sims = pairwise_sim3(observations, seed=seed)
    if visual_poses is not None:
        comps = [{v: (gtsam.Pose3(visual_poses[v]), 1.0) for v in views if v in visual_poses}]
        if not comps[0]:
            raise SolveError("--init: none of the predicted views has an initial pose")
    else:
        comps = spanning_tree_poses(views, observations, sims)
    usable, dropped = [], []
    for c in comps:
        frames = {split_view_id(v)[1] for v in c}
        (usable if len(frames) >= 2 else dropped).append(c)
    for c in dropped:
        log.warning("views %s: not co-visible with any other robot pose; left out of the solve", ", ".join(sorted(c)))
    if not usable:
        raise SolveError("no two robot poses see common structure: the co-visibility graph has no usable component")
    ee_T_cam, scales = hand_eye_closed_form(usable, base_T_ee, robot_file, seed=seed)
    base_T_cam, depth_scale = {}, {}
    for c, lam in zip(usable, scales):
        if not lam > 0:
            raise SolveError(f"closed-form metric scale is {lam:.3g} (not positive) for the component of view "
                             f"{next(iter(c))}: the robot motion does not explain the visual motion; check "
                             "robot_poses.csv units and pose direction")
        metric = {v: gtsam.Pose3(T.rotation(), lam * T.translation()) for v, (T, _) in c.items()}
        base_T_world = mean_pose([base_T_ee[split_view_id(v)[1]].compose(ee_T_cam[split_view_id(v)[0]]).compose(T.inverse())
                                  for v, T in metric.items()])
        for v, (_, s) in c.items():
            base_T_cam[v] = base_T_world.compose(metric[v])
            depth_scale[v] = lam * s
    inliers = [None if s is None else s[3] for s in sims]
    return Initialisation(base_T_cam, depth_scale, ee_T_cam, usable, inliers,
                          [{"view": v, "reason": "not co-visible with a view of any other robot pose (no pair with "
                                                 f"{MIN_INLIERS} matches that agree on one similarity)"}
                           for c in dropped for v in sorted(c)])
