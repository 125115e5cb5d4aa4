"""Where a live session's predictions come from, for the frames seen so far.

* :class:`RecordedPredictions`: a dataset's own ``predictions/<name>/`` (a simulator's, a network's
  run offline, an RGB-D frontend's): the subset of the frames so far.
* :class:`IncrementalPairwise`: the pairwise RGB frontend (``frontends/pairwise.py``) run as frames
  arrive. Its public steps are called on what is new only: features of the new frame's images
  (``features_for``), two-view geometry of the new pairs (``pair_geometries``), both kept in memory
  (and on disk with ``cache_dir``); then the robot checks, the robot-guided rescue of weakly
  connected views (a pair tried once is not tried again) run on all pairs so far; the per-view
  aggregation re-aggregates only the views whose pairs changed (a new pair can change an old view's
  depth; ``aggregate``'s cache keeps the others, as the same objects, so the engine rebuilds only
  the observations of the pairs that changed). :meth:`final` is the batch frontend
  itself (``pairwise_predictions``, from the same caches), so the last update solves exactly the
  predictions ``solve`` would.
"""

import itertools
import logging
import time

from calib3r_graph.errors import SolveError
from calib3r_graph.io.dataset import subset_dataset
from calib3r_graph.io.predictions import Predictions, subset_predictions, view_id

log = logging.getLogger(__name__)


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
        self.seconds = {}

    def _vids(self, ds, frames):
        frames = set(frames)
        return [view_id(c, f) for c in ds.cameras for f in ds.frames if f in frames and ds.image_path(c, f)]

    def add(self, ds, frame) -> list:
        """Features of the frame's views and the geometry of their pairs with every earlier view.
        ``ds``: the dataset of the frames so far (this one included). Returns the frame's views."""
        from calib3r_graph.frontends.pairwise import features_for, pair_geometries

        new = [v for v in self._vids(ds, [frame]) if v not in self.feats]
        t0 = time.perf_counter()
        self.feats.update(features_for(ds, new, self.opt, self.cache_dir, progress=False))
        t1 = time.perf_counter()
        vids = self._vids(ds, ds.frames)
        todo = [ab for ab in itertools.combinations(vids, 2) if ab not in self.geoms and (set(ab) & set(new))]
        self.geoms.update(pair_geometries(ds, self.feats, todo, self.opt, self.cache_dir, progress=False))
        self.seconds = {"features": t1 - t0, "pairs": time.perf_counter() - t1}
        return new

    def predictions(self, ds, frames) -> Predictions:
        """The frontend's aggregation over the pairs of ``frames`` (``ds``: the dataset so far)."""
        from calib3r_graph.frontends.pairwise import aggregate, match_noise_px, rescue_pairs, robot_consistent

        t0 = time.perf_counter()
        rescue_s = 0.0
        sub = subset_dataset(ds, frames)
        vids = self._vids(sub, sub.frames)
        feats = {v: self.feats[v] for v in vids if v in self.feats}
        candidates = [ab for ab in itertools.combinations(vids, 2) if ab in self.geoms]
        verified = {ab: self.geoms[ab] for ab in candidates if self.geoms[ab] is not None}
        kept, info = robot_consistent(verified, sub.base_T_ee, self.opt)
        if self.opt.rescue:
            todo = [ab for ab in candidates if ab not in self.rescued]
            tr = time.perf_counter()
            got = rescue_pairs(sub, feats, todo, kept, info, self.opt, progress=False)
            rescue_s = time.perf_counter() - tr
            for ab in todo:  # tried once (or not needed then): not tried again; views only gain pairs
                self.rescued[ab] = got.get(ab)
            extra = {ab: self.rescued[ab] for ab in candidates if self.rescued.get(ab) is not None}
            if extra:
                kept, info = robot_consistent({**verified, **extra}, sub.base_T_ee, self.opt)
        views, pairs, _ = aggregate(sub, feats, kept, self.opt, cache=self.aggregated)
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
            return self.predictions(ds, frames)
        return pairwise_predictions(subset_dataset(ds, frames), None, self.opt, self.cache_dir, progress=False)
