"""The views a solve leaves out, and why, in words: the views the scene factors of a round
cannot determine (weak pairs), the solve's state without them, the views the frontend dropped or
flagged (predictions' info.json: "unusable_views", "unusable_reasons", "pose_disagreements"), and
how messages name a view.
"""

import numpy as np

from calib3r_graph.errors import SolveError
from calib3r_graph.io.predictions import split_view_id
from calib3r_graph.solver.graph import MIN_FACTOR_MATCHES


def unsupported_views(views, observations, weights, min_matches=MIN_FACTOR_MATCHES) -> dict:
    """{view: reason} for the views that the scene factors of this round cannot determine.

    A pair enters the graph with at least ``min_matches`` matches of non-zero weight
    (graph.add_scene_factors). A view's depth scale is fixed only through such pairs, and a group
    of views linked by them is tied to the metric robot frame only when it spans two robot poses
    (the gauge argument of graph.py). A view without such a pair, or in a group at one pose, would
    leave the system indeterminate at the marginals (GTSAM names some variable of it, or the
    camera's metric scale it shares), however well LM converged: one view's weak pairs must not
    sink the solve of the others."""
    parent = {v: v for v in views}

    def root(v):
        while parent[v] != v:
            parent[v] = parent[parent[v]]
            v = parent[v]
        return v

    pairs, matches, usable = {}, {}, {}
    for o, w in zip(observations, weights):
        for v in (o.view_a, o.view_b):
            pairs[v] = pairs.get(v, 0) + 1
            matches[v] = matches.get(v, 0) + len(o)
        if int(np.count_nonzero(w > 0)) >= min_matches:
            usable[o.view_a] = usable.get(o.view_a, 0) + 1
            usable[o.view_b] = usable.get(o.view_b, 0) + 1
            parent[root(o.view_a)] = root(o.view_b)
    groups = {}
    for v in views:
        groups.setdefault(root(v), []).append(v)
    out = {}
    for members in groups.values():
        frames = {split_view_id(v)[1] for v in members}
        if len(frames) >= 2:
            continue
        for v in members:
            if not usable.get(v):
                out[v] = (f"none of its {pairs.get(v, 0)} pair(s) keeps {min_matches} of its {matches.get(v, 0)} "
                          "matches after robust re-weighting (they disagree with its robot pose and the other "
                          "views), so nothing determines its depth scale")
            else:
                out[v] = (f"its pairs link it only to {', '.join(sorted(set(members) - {v}))}, at the same robot "
                          "pose, so nothing ties their depth scale to the robot's motion")
    return out


def view_words(v: str) -> str:
    """'view cam0/0006 (camera cam0, frame 0006)': how messages name a view."""
    cam, frame = split_view_id(v)
    return f"view {v} (camera {cam}, frame {frame})"


def without_views(gone, keys, values, views, cameras, observations, conf, weights, inliers):
    """The solve's state without the views in ``gone``: their variables leave ``values`` and their
    pairs the lists; a camera left with no view leaves too."""
    for v in gone & set(views):
        for k in (keys.pose(v), keys.scale(v), keys.correction(v)):
            if values.exists(k):
                values.erase(k)
    views = [v for v in views if v not in gone]
    left = {split_view_id(v)[0] for v in views}
    for c in cameras:
        if c not in left:
            for k in (keys.hand_eye(c), keys.metric(c)):
                if values.exists(k):
                    values.erase(k)
    cameras = [c for c in cameras if c in left]
    if not views:
        raise SolveError("no view is left that the scene factors determine")
    keep = [i for i, o in enumerate(observations) if o.view_a not in gone and o.view_b not in gone]
    pick = lambda xs: [xs[i] for i in keep]
    return views, cameras, pick(observations), pick(conf), pick(weights), pick(inliers)


def _frontend_notes(preds) -> tuple[dict, dict]:
    """info.json's {view: reason} ("unusable_reasons") and {view: entry} ("pose_disagreements",
    OWNERS.md format); entries that do not fit that format are skipped (they are the frontend's
    notes, not data the solve needs)."""
    info = preds.info if isinstance(preds.info, dict) else {}
    reasons = info.get("unusable_reasons")
    reasons = {v: r for v, r in reasons.items() if isinstance(v, str) and isinstance(r, str)} \
        if isinstance(reasons, dict) else {}
    entries = info.get("pose_disagreements")
    disagree = {}
    for d in entries if isinstance(entries, list) else []:
        if (isinstance(d, dict) and isinstance(d.get("view"), str) and "/" in d["view"]
                and isinstance(d.get("rotation_deg"), (int, float))):
            disagree[d["view"]] = d
    return reasons, disagree


def dropped_by_frontend(preds) -> list:
    """[{"view", "reason"}] for the views the frontend could not use (predictions' info.json:
    "unusable_views", with "unusable_reasons" and "pose_disagreements" where it gives them)."""
    reasons, disagree = _frontend_notes(preds)
    unusable = preds.info.get("unusable_views") if isinstance(preds.info, dict) else None
    unusable = [v for v in unusable if isinstance(v, str)] if isinstance(unusable, list) else []
    out, seen = [], set()
    for v in unusable + list(reasons) + [v for v in disagree if v not in preds.views]:
        if v in seen or v in preds.views:
            continue
        seen.add(v)
        reason = pose_disagreement_text(disagree[v]) if v in disagree else \
            reasons.get(v) or "the frontend found no usable two-view geometry for it"
        out.append({"view": v, "reason": reason})
    return out


def pose_disagreements_kept(preds) -> list:
    """The diagnostics for poses the frontend found disagreeing with their image but kept in the
    predictions (the solve uses them: the user should still check them)."""
    _, disagree = _frontend_notes(preds)
    return [pose_disagreement_text(d) + "; kept in the solve: check this robot pose"
            for v, d in disagree.items() if v in preds.views]


def pose_disagreement_text(d: dict) -> str:
    """'pose of frame 0007 disagrees with its image by 8.5° / 44 mm (...)' from one entry of info.json's
    "pose_disagreements"."""
    cam, frame = split_view_id(d["view"])
    cam, frame = d.get("camera") or cam, d.get("frame") or frame
    t = d.get("translation_mm")
    size = f"{d['rotation_deg']:.1f}°" + (f" / {t:.0f} mm" if isinstance(t, (int, float)) else "")
    pairs = (f": the frontend rejected {d.get('pairs_rejected', '?')} of its {d['pairs_total']} pairs by the "
             "robot's motion" if isinstance(d.get("pairs_total"), int) else "")
    return f"pose of frame {frame} disagrees with its image by {size} (camera {cam}{pairs})"
