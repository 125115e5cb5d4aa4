"""The pairwise frontend's aggregation (steps 4-6 in ``frontend.py``): per view, every pair's depths
brought to one unit (:func:`view_depths`) and averaged by eq. 1, splatted into a depth map; the
matches whose depths agree at both ends, on a top-k co-visibility graph (:func:`aggregate`)."""

import logging

import numpy as np

from calib3r_graph.frontends.common import FULL_CONF_ANGLE_DEG, aggregate_pointmaps, covisibility_edges
from calib3r_graph.frontends.pairwise.options import Features, PairGeometry, PairwiseOptions
from calib3r_graph.io.predictions import PairMatches, ViewPrediction, split_view_id
from calib3r_graph.solver.observations import sample_bilinear

log = logging.getLogger(__name__)


def _weighted_median(x, w):
    order = np.argsort(x)
    cw = np.cumsum(w[order])
    return x[order][np.searchsorted(cw, 0.5 * cw[-1])]


def _angle_conf(angle):
    return np.clip(angle / np.radians(FULL_CONF_ANGLE_DEG), 0.05, 1.0)


def _median_angle_deg(g: PairGeometry) -> float:
    """The pair's median triangulation angle (deg): ``two_view_geometry`` wrote exactly this number
    (``np.degrees(np.median(angle))`` of the angles it kept) into its stats; computed where absent."""
    m = g.stats.get("median_angle_deg")
    return float(np.degrees(np.median(g.angle))) if m is None else m


def view_depths(vid, feats: Features, geoms: dict, opt: PairwiseOptions):
    """Per-keypoint depth of one view from its pairs, every pair brought to one unit.

    Returns (kp ids (M,), depth (M,), conf (M,), {pair: log scale}) — the scale that maps the
    pair's unit to the view's — or None when no pair gives depth."""
    entries = []  # (pair, kp ids, depth, angle-conf)
    for ab, g in geoms.items():
        if vid not in ab or _median_angle_deg(g) < opt.min_pair_angle_deg:
            continue
        idx, d = (g.ia, g.depth_a) if ab[0] == vid else (g.ib, g.depth_b)
        entries.append((ab, feats.kp_id[idx], d, _angle_conf(g.angle)))
    if not entries:
        return None
    # Reference: of the three pairs with the most (angle-weighted) triangulated points, the one
    # the most other pairs agree with (a wrong geometry with many points must not set the unit).
    order = sorted(range(len(entries)), key=lambda k: -entries[k][3].sum())
    n_kp = int(feats.kp_id.max()) + 1 if len(feats.kp_id) else 0
    prep = _AlignInputs(entries, n_kp)
    best = None
    for ref in order[:3]:
        scales = _align(vid, entries, ref, order, n_kp, opt, prep)
        weight = sum(entries[k][3].sum() for k in range(len(entries)) if entries[k][0] in scales)
        if best is None or weight > best[0]:
            best = (weight, scales)
        if len(scales) == len(entries):
            break  # every pair aligned: no later reference can weigh more (a sum of fewer positive terms)
    scales = best[1]
    # Eq. 1 on the keypoints, after dropping entries far from each keypoint's weighted median.
    used = [k for k in range(len(entries)) if entries[k][0] in scales]
    ids_all = np.unique(np.concatenate([entries[k][1] for k in used]))
    P, M = len(used), len(ids_all)
    D = np.zeros((P, 1, M))
    C = np.zeros((P, 1, M))
    for p, k in enumerate(used):
        ab, ids, d, c = entries[k]
        j = np.searchsorted(ids_all, ids)
        o = np.argsort(c)  # the same keypoint twice in one pair (two orientations): the better one wins
        D[p, 0, j[o]] = d[o] * np.exp(scales[ab])
        C[p, 0, j[o]] = c[o]
    logD = np.log(np.where(D[:, 0] > 0, D[:, 0], 1.0))
    med = _weighted_median_columns(logD, C[:, 0])
    C[:, 0] = np.where(np.abs(logD - med[None]) > opt.max_depth_spread, 0.0, C[:, 0])
    depth, conf = aggregate_pointmaps(D, C)
    ok = depth[0] > 0
    return ids_all[ok], depth[0][ok].astype(np.float64), conf[0][ok].astype(np.float64), scales


class _AlignInputs:
    """What :func:`_align` reads of a view's entries, computed once for its three reference tries:
    each entry's log depths and its kp-id counts (P, n_kp), so that the keypoints each pending pair
    shares with those already aligned are one matrix-vector product, not one gather per pair and
    step."""

    def __init__(self, entries, n_kp):
        self.logd = [np.log(e[2]) for e in entries]
        self.counts = (np.array([np.bincount(e[1], minlength=n_kp) for e in entries], np.float64) if n_kp
                       else np.zeros((len(entries), 0)))


def _align(vid, entries, ref, order, n_kp, opt, prep=None):
    """{pair: log scale into ref's unit} of the pairs that agree with ``ref``, greedily: the pair
    sharing most keypoints with those already aligned goes next (ties: the earlier in ``order``)."""
    prep = prep or _AlignInputs(entries, n_kp)
    acc_w = np.zeros(n_kp)
    acc_logd = np.zeros(n_kp)
    scales = {}

    def add(k, log_s):
        ab, ids, d, c = entries[k]
        np.add.at(acc_w, ids, c)
        np.add.at(acc_logd, ids, c * (prep.logd[k] + log_s))
        scales[ab] = log_s

    add(ref, 0.0)
    pending = np.array([k for k in order if k != ref], int)  # in order: argmax's first maximum breaks ties
    while len(pending):
        shared = (prep.counts @ (acc_w > 0))[pending]
        at = int(np.argmax(shared))
        k = int(pending[at])
        pending = pending[pending != k]
        if shared[at] < opt.min_shared:
            break  # nothing left overlaps the aligned pairs
        ab, ids, d, c = entries[k]
        m = acc_w[ids] > 0
        im = ids[m]
        diff = acc_logd[im] / acc_w[im] - prep.logd[k][m]
        w = c[m] * np.minimum(acc_w[im], 1.0)
        log_s = _weighted_median(diff, w)
        mad = 1.4826 * _weighted_median(np.abs(diff - log_s), w)
        if mad > opt.max_scale_mad:
            log.debug("%s: pair %s-%s gives no depth (scale ratios scatter by %.1f %%)", vid, *ab, 100 * mad)
            continue
        add(k, log_s)
    return scales


def _weighted_median_columns(x, w):
    """Weighted median of each column of x (P, M) under weights w (P, M); zero weight = absent."""
    key = np.where(w > 0, x, np.inf)
    order = np.argsort(key, axis=0)
    xs, ws = np.take_along_axis(key, order, 0), np.take_along_axis(w, order, 0)
    cw = np.cumsum(ws, axis=0)
    k = np.argmax(cw >= 0.5 * cw[-1:], axis=0)
    return xs[k, np.arange(x.shape[1])]


def _unchanged_view(hit, feats: Features, res):
    """(ViewPrediction, info) of the last aggregation of this view where ``res`` (view_depths' result,
    its pairs having changed) gives the same keypoints, depths and confidences: the depth maps would
    be the same arrays, so the same object is kept (no new maps, no re-sampled matches). Else None."""
    if hit is None or hit[0] is not feats or hit[3] is None or hit[2] is None or res is None:
        return None
    if not all(x.shape == y.shape and np.array_equal(x, y) for x, y in zip(hit[2][:3], res[:3])):
        return None
    view, view_info = hit[3]
    return view, (view_info if view_info["pairs"] == len(res[3]) else {**view_info, "pairs": len(res[3])})


def _still_growing(hit, feats: Features, mine, regrow) -> bool:
    """Whether a view's last aggregation (``hit``: aggregate's cache entry) stands for its pairs
    ``mine`` under ``regrow``: the same features, a usable result, each pair it came from still there
    with the same geometry, and fewer than ``regrow`` times as many pairs now."""
    if hit is None or hit[0] is not feats or hit[2] is None or hit[3] is None or len(mine) >= regrow * len(hit[1]):
        return False
    now = dict(mine)
    return all(now.get(ab) is g for ab, g in hit[1])


def _pair_end(cache, ab, end, g, feats: Features, view):
    """One end of a pair's match check: its matches' pixels, whether the view's depth map has depth
    there (all four neighbours), and the log ratio of that depth to the pair's own. Kept while the
    pair's geometry and that view's prediction are the same objects: a new depth map at one end
    re-samples only that end."""
    key = ("end", *ab, end)
    hit = cache.get(key)
    if hit is not None and hit[0] is g and hit[1] is view:
        return hit[2]
    uv = feats.uv[g.ia if end == 0 else g.ib]
    d, ok = sample_bilinear(view.depth, uv)
    with np.errstate(divide="ignore", invalid="ignore"):
        lr = np.log(d) - np.log(g.depth_a if end == 0 else g.depth_b)
    cache[key] = (g, view, (uv, ok, lr))
    return cache[key][2]


def aggregate(ds, feats: dict, geoms: dict, opt: PairwiseOptions, known_reasons: dict | None = None,
              cache: dict | None = None, regrow: float | None = None):
    """(views {vid: ViewPrediction}, pairs [PairMatches], info) from verified pair geometries.
    ``info["reasons"]`` says in one line why each of ``info["unusable"]`` is left out;
    ``known_reasons`` are the views already explained (and warned about) by the caller.

    ``cache`` (a dict the caller keeps, e.g. a live session adding frames): a view whose features and
    pair geometries (the same objects, in the same order) are those of the last call is not
    aggregated again, and a pair whose geometry and both views are unchanged keeps its matches;
    the results are the same objects as before, so a caller can tell what changed by identity. A
    view whose pairs changed but whose keypoint depths come out the same keeps its prediction too,
    and a pair re-samples only the end whose prediction is new.

    ``regrow`` (with ``cache``): a view keeps its last aggregation while every pair it was aggregated
    from is still there, unchanged, and it has fewer than ``regrow`` times as many pairs; a new pair's
    matches then meet the depth that view had (a live session: ``live/sources.py`` says why)."""
    known_reasons = known_reasons or {}
    cache = {} if cache is None else cache
    views, info = {}, {"views": {}, "unusable": [], "reasons": {}}
    for vid in sorted(feats):
        cam = ds.cameras[split_view_id(vid)[0]]
        mine = [(ab, g) for ab, g in geoms.items() if vid in ab]
        hit = cache.get(("view", vid))
        if hit is not None and hit[0] is feats[vid] and len(hit[1]) == len(mine) and all(
                ab == ab2 and g is g2 for (ab, g), (ab2, g2) in zip(hit[1], mine)):
            res, done = hit[2], hit[3]
        elif regrow and _still_growing(hit, feats[vid], mine, regrow):
            res, done = hit[2], hit[3]  # (the cache keeps the pairs it was aggregated from)
        else:  # view_depths reads only the view's own pairs, in geoms' order
            res = view_depths(vid, feats[vid], dict(mine), opt)
            done = _unchanged_view(hit, feats[vid], res)
            cache[("view", vid)] = (feats[vid], mine, res, done)
        if res is None or len(res[0]) < opt.min_view_points:
            n = 0 if res is None else len(res[0])
            info["unusable"].append(vid)
            if vid in known_reasons:
                info["reasons"][vid] = known_reasons[vid]
                continue
            n_pairs = sum(vid in ab for ab in geoms)
            info["reasons"][vid] = (f"no usable two-view geometry ({n_pairs} verified pair(s) agree with the robot's "
                                    f"motion, {n} triangulated points)")
            log.warning("view %s: %s; left out of the predictions, the others go on", vid, info["reasons"][vid])
            continue
        if done is not None:
            views[vid], info["views"][vid] = done
            continue
        ids, depth_kp, conf_kp, scales = res
        # one feature per kp id: its (full-resolution) location
        first = np.full(int(feats[vid].kp_id.max()) + 1, -1)
        first[feats[vid].kp_id[::-1]] = np.arange(len(feats[vid].kp_id))[::-1]
        uv = feats[vid].uv[first[ids]]
        depth = np.zeros((cam.height, cam.width), np.float32)
        conf = np.zeros((cam.height, cam.width), np.float32)  # zeros, not zeros_like: untouched pages stay unwritten
        x0, y0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (x0 >= 0) & (y0 >= 0) & (x0 < cam.width - 1) & (y0 < cam.height - 1)
        order = np.argsort(conf_kp[ok])  # where splats overlap, the most confident one wins
        at = y0[ok][order] * cam.width + x0[ok][order]  # flat pixel index, written in the same order
        d_kp, c_kp = depth_kp[ok][order], conf_kp[ok][order]
        for dx in (0, 1):
            for dy in (0, 1):
                depth.ravel()[at + (dy * cam.width + dx)] = d_kp
                conf.ravel()[at + (dy * cam.width + dx)] = c_kp
        views[vid] = ViewPrediction(depth, conf, cam.K)
        info["views"][vid] = {"points": int(ok.sum()), "pairs": len(scales)}
        cache[("view", vid)] = cache[("view", vid)][:3] + ((views[vid], info["views"][vid]),)
    # Matches: every verified pair's, where the depths written at both ends agree with the pair's
    # own triangulation up to one scale per end (a match along a repeated texture's epipolar
    # line, or a splat a neighbouring keypoint overwrote, does not); scored by how many do.
    cand, scores = {}, {}
    for (a, b), g in geoms.items():
        if a not in views or b not in views:
            continue
        hit = cache.get(("pair", a, b))
        if hit is not None and hit[0] is g and hit[1] is views[a] and hit[2] is views[b]:
            if hit[3] is not None:
                cand[(a, b)], scores[(a, b)] = hit[3], len(hit[3].conf)
            continue
        cache[("pair", a, b)] = (g, views[a], views[b], None)
        uv_a, ok_a, la = _pair_end(cache, (a, b), 0, g, feats[a], views[a])
        uv_b, ok_b, lb = _pair_end(cache, (a, b), 1, g, feats[b], views[b])
        ok = ok_a & ok_b
        if ok.sum() < 20:
            continue
        keep = ok.copy()
        keep[ok] = ((np.abs(la[ok] - np.median(la[ok])) < opt.max_depth_spread)
                    & (np.abs(lb[ok] - np.median(lb[ok])) < opt.max_depth_spread))
        if keep.sum() >= 20:
            cand[(a, b)] = PairMatches(a, b, uv_a[keep], uv_b[keep], g.conf[keep])
            scores[(a, b)] = int(keep.sum())
            cache[("pair", a, b)] = (g, views[a], views[b], cand[(a, b)])
    edges = covisibility_edges(scores, sorted(views), opt.neighbours)

    def flipped(e):
        c, hit = cand[e[::-1]], cache.get(("flipped", *e))
        if hit is None or hit[0] is not c:
            hit = cache[("flipped", *e)] = (c, PairMatches(e[0], e[1], c.uv_b, c.uv_a, c.conf))
        return hit[1]

    pairs = [cand[e] if e in cand else flipped(e) for e in edges]
    for vid in sorted(views):
        if not any(vid in (p.view_a, p.view_b) for p in pairs):
            info["unusable"].append(vid)
            info["reasons"][vid] = "its depth is shared with no other view"
            log.warning("view %s: its depth is shared with no other view; left out of the predictions", vid)
    used = {v for p in pairs for v in (p.view_a, p.view_b)}
    views = {v: p for v, p in views.items() if v in used}
    return views, pairs, info
