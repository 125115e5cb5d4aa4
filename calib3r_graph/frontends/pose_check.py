"""A robot pose that disagrees with its image, for the pairwise frontend (frontends/pairwise/).

A view most of whose pairs the robot's motion rejects, while its partners' other pairs pass, is
the one to blame (:func:`blamed_views`). It is set aside and the other pairs are checked against
the robot again without it; then its pairs with good views measure how far its robot pose is from
what its images show (:func:`pose_disagreement`): the flange rotation the images imply against the
robot's (deg) and, where two good partners see it from directions far enough apart, the flange
position (mm). One rotation for every partner means a wrong pose; scattered ones mean wrong
matches, and its pairs go back to the checks. :func:`find_pose_disagreements` returns the records
and one-line reasons the frontend writes to ``info.json`` (``pose_disagreements``,
``unusable_reasons``) and warns about.

The robot check itself (``pairwise.robot_consistent``) is passed in, so this module does not
import the frontend.
"""

import logging

import numpy as np

from calib3r_graph.frontends.common import FULL_CONF_ANGLE_DEG
from calib3r_graph.geometry import project_to_so3, rotation_angle_deg
from calib3r_graph.io.predictions import split_view_id

log = logging.getLogger(__name__)


def _same_camera(ab):
    return split_view_id(ab[0])[0] == split_view_id(ab[1])[0]


def blamed_views(verified: dict, kept: dict) -> list:
    """Views whose pairs the robot's motion rejects because of the view itself, worst first.

    A pair the robot rejects has two ends; the one to blame is the view most of whose pairs are
    rejected (at least two: one pair cannot tell its ends apart) while the partners of those
    rejected pairs have their other pairs mostly accepted. Once a view is blamed its pairs no
    longer count against its partners, so a good view that shared pairs with it is not blamed
    too."""
    pairs = {ab for ab in verified if _same_camera(ab)}
    rejected = {ab for ab in pairs if ab not in kept}
    blamed = []
    while True:
        n, r = {}, {}
        for ab in pairs:
            for v in ab:
                n[v] = n.get(v, 0) + 1
                r[v] = r.get(v, 0) + (ab in rejected)
        best = None
        for v in n:
            if r[v] < 2 or 2 * r[v] <= n[v]:
                continue
            accepted = []  # per partner of a rejected pair: the share of its other pairs accepted
            for ab in pairs & rejected:
                if v in ab:
                    u = ab[1] if ab[0] == v else ab[0]
                    others = [p for p in pairs if u in p and v not in p]
                    if others:
                        accepted.append(np.mean([p not in rejected for p in others]))
            key = (r[v] / n[v], r[v])
            if accepted and np.median(accepted) > 0.5 and (best is None or key > best[0]):
                best = (key, v)
        if best is None:
            return blamed
        blamed.append(best[1])
        pairs = {ab for ab in pairs if best[1] not in ab}


def pose_disagreement(v: str, verified: dict, bad: set, base_T_ee: dict, hand_eye: dict, tol_deg: float) -> dict | None:
    """How far view v's robot pose is from the one its image gives, through its pairs with good views.

    With the rough hand-eye ``X`` (found without the bad views) each good partner u places v's
    camera: rotation ``R_cam_u R_uv`` and, along the pair's translation direction, a ray from u's
    camera centre. The flange rotation this implies, ``R_cam_v R_X^T``, differs from the robot's by
    ``D_u = R_ee_v^T R_ee_v_img``: one rotation for every partner if the pose is wrong (the
    ``rotation_deg`` is the angle of the chordal mean of those within ``tol_deg`` of the one
    closest to the others), scattered if the pair geometries are wrong instead (``scatter_deg``,
    the median angle of the D_u from that mean). The rays from two or more partners that see v at least
    ``FULL_CONF_ANGLE_DEG`` apart meet at v's camera centre (the scale comes from the good views'
    own robot poses): ``translation_mm`` is the distance of the flange this implies from the
    robot's, else None; ``baseline_mm`` is the median distance of those partners' cameras from v's.
    None when v has no pair with a good view or no rough hand-eye rotation."""
    if "rotation" not in hand_eye:
        return None
    R_X = np.array(hand_eye["rotation"])
    t_X = np.array(hand_eye["translation"]) if "translation" in hand_eye else None
    ee_v = base_T_ee[split_view_id(v)[1]]
    D, rays = [], []
    for (a, b), g in verified.items():
        if v not in (a, b) or not _same_camera((a, b)):
            continue
        u = b if a == v else a
        if u in bad:
            continue
        ee_u = base_T_ee[split_view_id(u)[1]]
        R_cam_u = ee_u.rotation().matrix() @ R_X
        # x_b = R x_a + t: b_T_a = (R, t); the other end's centre in this end's frame is t or -R^T t
        R_uv, d = (g.R, g.t) if a == v else (g.R.T, -g.R.T @ g.t)
        D.append(ee_v.rotation().matrix().T @ R_cam_u @ R_uv @ R_X.T)
        if t_X is not None:
            rays.append((ee_u.translation() + ee_u.rotation().matrix() @ t_X, R_cam_u @ d / np.linalg.norm(d)))
    if not D:
        return None
    D = np.array(D)
    # robustly: the D_u closest to the others (a wrong pair geometry among v's pairs gives a stray one),
    # then the chordal mean of those within tol_deg of it
    between = np.array([[rotation_angle_deg(Di.T @ Dj) for Dj in D] for Di in D])
    inl = between[np.argmin(np.median(between, axis=1))] <= tol_deg
    mean = project_to_so3(D[inl].sum(0))
    dev = np.array([rotation_angle_deg(mean.T @ Du) for Du in D])
    out = {"rotation_deg": rotation_angle_deg(mean), "scatter_deg": float(np.median(dev)), "translation_mm": None,
           "partners": len(D)}
    good = [ray for ray, e in zip(rays, dev) if e <= tol_deg] if rays else []
    if len(good) >= 2:
        dirs = np.array([d for _, d in good])
        spread = np.degrees(np.arccos(np.clip(dirs @ dirs.T, -1, 1))).max()
        if spread >= FULL_CONF_ANGLE_DEG:
            # closest point to the rays: sum (I - d d^T) (p - c) = 0
            P = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]
            c = np.array([c for c, _ in good])
            p = np.linalg.solve(P.sum(0), np.einsum("nij,nj->i", P, c))
            t_ee_img = p - (ee_v.rotation().matrix() @ mean) @ t_X  # t_ee = t_cam - R_ee t_X
            out["translation_mm"] = float(1e3 * np.linalg.norm(t_ee_img - ee_v.translation()))
            out["baseline_mm"] = float(1e3 * np.median(np.linalg.norm(c - p, axis=1)))
    return out


def find_pose_disagreements(verified: dict, kept: dict, base_T_ee: dict, opt, robot_consistent):
    """(kept, robot_info, [pose disagreement records], {view: reason}) after checking whether the
    views most of whose pairs the robot rejects have a wrong pose.

    The blamed views (:func:`blamed_views`) are set aside and every other pair is checked against
    the robot again, so a view that failed only because of them is re-examined with a rough
    hand-eye they no longer bend. A blamed view whose pairs with good views all imply one flange
    rotation (within twice ``rotation_tol_deg``, the scatter good pairs have) has a pose that
    disagrees with its image, if by more than the checks tolerate; one whose pairs scatter, or agree
    with its pose, is a view some of whose matches are wrong, and its pairs go back to the checks.
    ``opt``: the frontend's PairwiseOptions; ``robot_consistent(geoms, base_T_ee, opt) -> (kept, info)``:
    the frontend's robot check (pairwise.robot_consistent)."""
    blamed = blamed_views(verified, kept)
    if not blamed:
        return kept, None, [], {}
    total = {v: sum(v in ab for ab in verified if _same_camera(ab)) for v in blamed}
    rejected = {v: sum(v in ab and ab not in kept for ab in verified if _same_camera(ab)) for v in blamed}
    without = lambda views: {ab: g for ab, g in verified.items() if not set(ab) & set(views)}  # noqa: E731
    kept, info = robot_consistent(without(blamed), base_T_ee, opt)
    records, reasons, bad = [], {}, set(blamed)
    for v in blamed:
        c, f = split_view_id(v)
        m = pose_disagreement(v, verified, bad, base_T_ee, info["hand_eye"].get(c, {}), 2 * opt.rotation_tol_deg)
        why = None
        if m is None:
            why = "no pair with a good view"
        elif m["scatter_deg"] > 2 * opt.rotation_tol_deg:
            why = f"they scatter by {m['scatter_deg']:.1f} deg"
        elif m["rotation_deg"] <= opt.rotation_tol_deg and (m["translation_mm"] is None or m["translation_mm"] <= m[
                "baseline_mm"] * np.sin(np.radians(opt.translation_tol_deg))):
            # within what the checks tolerate: a good pair's rotation may be rotation_tol_deg off, and a
            # translation error turns the directions seen from the partners by translation_mm / baseline
            why = (f"its pairs with good views agree with its pose within {m['rotation_deg']:.2f} deg"
                   + ("" if m["translation_mm"] is None else f" and {m['translation_mm']:.1f} mm"))
        if why is not None:
            bad.discard(v)
            log.info("view %s: %d of its %d pairs disagree with the robot's motion, but not by one pose error "
                     "(%s): its pairs stay in the checks", v, rejected[v], total[v], why)
            continue
        mm = "" if m["translation_mm"] is None else f" and {m['translation_mm']:.0f} mm"
        records.append({"view": v, "camera": c, "frame": f, "rotation_deg": round(m["rotation_deg"], 3),
                        "translation_mm": None if m["translation_mm"] is None else round(m["translation_mm"], 2),
                        "pairs_rejected": rejected[v], "pairs_total": total[v]})
        reasons[v] = (f"the robot pose of frame {f} disagrees with its image by {m['rotation_deg']:.1f} deg{mm} "
                      f"({rejected[v]} of its {total[v]} pairs disagree with the robot's motion, its partners' "
                      "other pairs agree): check that pose")
        log.warning("view %s: %s; the view is left out, the others go on", v, reasons[v])
    if bad != set(blamed):
        kept, info = robot_consistent(without(bad), base_T_ee, opt)
    return kept, info, records, reasons
