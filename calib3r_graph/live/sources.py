"""Where a live session's predictions come from, for the frames seen so far.

* :class:`RecordedPredictions`: a dataset's own ``predictions/<name>/`` (a simulator's, a network's
  run offline, an RGB-D frontend's): the subset of the frames so far.
* :class:`IncrementalPairwise`: the pairwise RGB frontend (``frontends/pairwise/``) run as frames
  arrive. Its public steps are called on what is new only: features of the new frame's images
  (``features_for``), two-view geometry of the new pairs (``pair_geometries``), both kept in memory
  (and on disk with ``cache_dir``). The new pairs are the batch frontend's pair selection
  (``frontends/pair_selection.py``) applied to the new views: each new view's ``partners`` best
  earlier views by the same ranking (VLAD image similarity and the flanges' rotation / distance
  ranks), the earlier views that rank it among their ``partners`` best (the batch rule is
  symmetric), its rig pairs, then up to ``more_rounds`` rounds of ``PairSelection.more`` (the next
  partners of weakly connected views, pairs across parts of the graph) restricted to pairs with a
  new view, at most ``partners`` a round per new view. So an update matches the new view with about
  15 earlier views at 10 partners, not every one (docs/live.md: 435 -> 340 pairs on rwhe_kuka_1).
  Then the robot checks, the robot-guided rescue of weakly connected views (a pair tried once is not
  tried again) run on the pairs so far; the per-view aggregation re-aggregates only the views whose
  pairs changed (a new pair can change an old view's depth; ``aggregate``'s cache keeps the others,
  as the same objects, so the engine rebuilds only the observations of the pairs that changed), and
  an old view only once its pairs have grown by ``REGROW`` since it was last aggregated
  (:data:`REGROW`): until then a new pair's matches meet the depth that view had.
  :meth:`final` is the batch frontend itself (``pairwise_predictions``, from the same caches), so
  the last update solves exactly the
  predictions ``solve`` would.
"""

import itertools
import logging
import time

import numpy as np

from calib3r_graph.errors import SolveError
from calib3r_graph.io.dataset import subset_dataset
from calib3r_graph.io.predictions import Predictions, subset_predictions, view_id

log = logging.getLogger(__name__)

# An old view is aggregated again once it has REGROW times the pairs it was last aggregated from
# (aggregate's ``regrow``), so each view is aggregated about log2(its pairs) times in a session, not
# once for every frame that pairs with it (each new frame pairs with about 15 earlier views, and the
# engine then rebuilt the observations, whitening and terms of every pair of each). Measured
# (docs/live-notes.md, "What an update recomputes"): 1-7 % fewer matches in the predictions at 9-30 frames
# of rwhe_kuka_1 and rwhe_kuka_2 (a new pair keeps its matches where the old view already had depth);
# rwhe_kuka_1's median update at 20-30 frames 0.69-0.74 -> 0.49-0.54 CPU s in the solver and
# 1.47-1.51 -> 0.94-0.99 s wall with the frontend; the same frames to 3 mm and 3-sigma cover there, and
# fewer on rwhe_kuka_2; its cost: tabb_ds1's guided starts reach that result's own sigma after 25
# frames instead of 17 (its rotation error hovers at that tolerance).
REGROW = 2.0


class RecordedPredictions:
    def __init__(self, preds: Predictions):
        self.preds = preds
        self.seconds = {}

    def frame_views(self, frame) -> list:
        return [v for v in self.preds.views if v.split("/", 1)[1] == frame]

    def add(self, ds, frame):
        """Nothing to compute; the frame must have predictions."""
        self.seconds = {"features": 0.0, "pairs": 0.0}
        return self.frame_views(frame)

    def predictions(self, ds, frames) -> Predictions:
        return subset_predictions(self.preds, frames)

    final = predictions


class IncrementalPairwise:
    def __init__(self, opt=None, cache_dir=None):
        from calib3r_graph.frontends.pairwise import PairwiseOptions

        self.opt = opt or PairwiseOptions()
        self.cache_dir = cache_dir
        self.feats, self.geoms, self.rescued = {}, {}, {}
        self.aggregated = {}  # aggregate()'s cache: views and pairs whose inputs did not change
        self.regrow = REGROW  # aggregate()'s regrow (None: an old view is aggregated again at every new pair)
        self.vocabulary = None  # (views it was learnt from, k-means centres) of the VLAD similarity
        self.vlads = {}  # view -> VLAD descriptor over that vocabulary
        # new view -> the pairs its update matched: [its own picks, the earlier views' picks of it, then
        # each more round's]
        self.picked = {}
        self._robot = None  # (key, result) of the last robot_consistent call
        self.seconds = {}

    def _vids(self, ds, frames):
        frames = set(frames)
        return [view_id(c, f) for c in ds.cameras for f in ds.frames if f in frames and ds.image_path(c, f)]

    def _selection(self, ds, vids):
        """The batch frontend's PairSelection over the views so far. Its VLAD vocabulary is learnt again
        only when the views have doubled since it was learnt (k-means on 20000 descriptors costs
        about 0.5 s, one update's budget): the views it was learnt from are then always at least half
        of those it describes, and it is learnt log2(N) times in a session, not N times."""
        from calib3r_graph.frontends.pair_selection import PairSelection, vlad, vocabulary

        if self.vocabulary is None or len(vids) >= 2 * self.vocabulary[0]:
            self.vocabulary = (len(vids), vocabulary([self.feats[v].desc for v in vids]))
            self.vlads = {}
        todo = [v for v in vids if v not in self.vlads]
        if todo and self.vocabulary[1] is not None:
            self.vlads.update(zip(todo, vlad([self.feats[v].desc for v in todo], centres=self.vocabulary[1])))
        V = (np.array([self.vlads[v] for v in vids]) if self.vocabulary[1] is not None
             else np.zeros((len(vids), 1), np.float32))
        return PairSelection(vids, None, ds.base_T_ee, self.opt.partners, vlads=V)

    def _verified(self, vids) -> dict:
        return {ab: self.geoms[ab] for ab in itertools.combinations(vids, 2) if self.geoms.get(ab) is not None}

    def _robot_consistent(self, geoms: dict, base_T_ee: dict):
        """``robot_consistent`` of the pairs, kept while the pairs (the same objects) and poses are the
        same: the pair selection's rounds and the aggregation after them ask for the same call."""
        from calib3r_graph.frontends.pairwise import robot_consistent

        key = (tuple((ab, id(g)) for ab, g in geoms.items()), tuple((f, id(T)) for f, T in base_T_ee.items()))
        if self._robot is None or self._robot[0] != key:
            self._robot = (key, robot_consistent(geoms, base_T_ee, self.opt), geoms, base_T_ee)  # keep ids alive
        return self._robot[1]

    def add(self, ds, frame) -> list:
        """Features of the frame's views and the geometry of their selected pairs with earlier views
        (the module's docstring). ``ds``: the dataset of the frames so far (this one included).
        Returns the frame's views."""
        from calib3r_graph.frontends.pairwise import features_for, pair_geometries

        new = [v for v in self._vids(ds, [frame]) if v not in self.feats]
        t0 = time.perf_counter()
        self.feats.update(features_for(ds, new, self.opt, self.cache_dir, progress=False))
        t1 = time.perf_counter()
        vids = self._vids(ds, ds.frames)
        p = self.opt.partners
        if p <= 0 or p >= len(vids) - 1:  # as the batch frontend: every pair
            todo = [ab for ab in itertools.combinations(vids, 2) if ab not in self.geoms and (set(ab) & set(new))]
            self.picked.update({v: [[ab for ab in todo if v in ab], []] for v in new})
            self.geoms.update(pair_geometries(ds, self.feats, todo, self.opt, self.cache_dir, progress=False))
        elif new:
            sel = self._selection(ds, vids)
            first = {v: [ab for ab in sel.picks(v) if ab not in self.geoms] for v in new}
            others = {v: [ab for ab in sel.chosen_by(v) if ab not in self.geoms and ab not in first[v]] for v in new}
            todo = sorted({ab for v in new for ab in first[v] + others[v]})
            self.picked.update({v: [first[v], others[v]] for v in new})
            self.geoms.update(pair_geometries(ds, self.feats, todo, self.opt, self.cache_dir, progress=False))
            for _ in range(self.opt.more_rounds):
                kept, _ = self._robot_consistent(self._verified(vids), ds.base_T_ee)
                more = [ab for ab in sel.more(self.geoms, kept, self.opt.rescue_below) if set(ab) & set(new)]
                todo = set()
                for v in new:  # at most `partners` a round per new view, its own best first
                    rank = sel.rank(v)
                    mine = sorted((ab for ab in more if v in ab and ab not in todo),
                                  key=lambda ab: rank.get(ab[1] if ab[0] == v else ab[0], len(rank)))[:p]
                    self.picked[v].append(mine)
                    todo.update(mine)
                if not todo:
                    break
                self.geoms.update(pair_geometries(ds, self.feats, sorted(todo), self.opt, self.cache_dir,
                                                  progress=False))
        self.seconds = {"features": t1 - t0, "pairs": time.perf_counter() - t1}
        return new

    def predictions(self, ds, frames, every_view=False) -> Predictions:
        """The frontend's aggregation over the pairs of ``frames`` (``ds``: the dataset so far);
        ``every_view``: every view whose pairs changed is aggregated again (else an old view waits for
        ``self.regrow``)."""
        from calib3r_graph.frontends.pairwise import aggregate, match_noise_px, rescue_pairs

        t0 = time.perf_counter()
        rescue_s = 0.0
        sub = subset_dataset(ds, frames)
        vids = self._vids(sub, sub.frames)
        feats = {v: self.feats[v] for v in vids if v in self.feats}
        candidates = [ab for ab in itertools.combinations(vids, 2) if ab in self.geoms]
        verified = self._verified(vids)
        kept, info = self._robot_consistent(verified, sub.base_T_ee)
        if self.opt.rescue:
            todo = [ab for ab in candidates if ab not in self.rescued]
            tr = time.perf_counter()
            got = rescue_pairs(sub, feats, todo, kept, info, self.opt, progress=False)
            rescue_s = time.perf_counter() - tr
            for ab in todo:  # tried once (or not needed then): not tried again; views only gain pairs
                self.rescued[ab] = got.get(ab)
            extra = {ab: self.rescued[ab] for ab in candidates if self.rescued.get(ab) is not None}
            if extra:
                kept, info = self._robot_consistent({**verified, **extra}, sub.base_T_ee)
        views, pairs, _ = aggregate(sub, feats, kept, self.opt, cache=self.aggregated,
                                    regrow=None if every_view else self.regrow)
        # the robot-guided matching of the new pairs is pair geometry, not aggregation
        self.seconds["rescue"] = rescue_s
        self.seconds["aggregation"] = time.perf_counter() - t0 - rescue_s
        if not pairs:
            raise SolveError("pairwise: no two of the images so far share enough verified, triangulated matches")
        return Predictions("pairwise", {"source": "calib3r-graph pairwise (live)", "metric_depth": False,
                                        "match_noise_px": match_noise_px(kept)}, views, pairs)

    def final(self, ds, frames) -> Predictions:
        """The batch frontend on ``frames``, as ``solve`` would run it (from the caches)."""
        from calib3r_graph.frontends.pairwise import pairwise_predictions

        if self.cache_dir is None:
            return self.predictions(ds, frames, every_view=True)
        return pairwise_predictions(subset_dataset(ds, frames), None, self.opt, self.cache_dir, progress=False)
