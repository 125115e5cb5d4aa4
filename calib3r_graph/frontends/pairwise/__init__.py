"""Pairwise RGB frontend: two-view geometry per co-visible pair, aggregated per view. What it does,
step by step, is told in ``frontend.py``; each step lives in one module, each importing only those
above it in this list:

- ``options.py``: :class:`PairwiseOptions`, what the steps hand on (:class:`Features`,
  :class:`PairGeometry`) and their shared helpers (the on-disk cache's keys, a threaded map);
- ``features.py``: RootSIFT features once per image, cached (:func:`features_for`);
- ``geometry.py``: two-view geometry once per pair, cached (:func:`two_view_geometry`,
  :func:`pair_geometries`), and guided matching along epipolar lines;
- ``robot.py``: the robot's help, never as ground truth (:func:`robot_consistent`,
  :func:`rescue_pairs`);
- ``aggregation.py``: per-view scale alignment and eq. 1, and the matches kept (:func:`aggregate`);
- ``frontend.py``: the steps run in order (:func:`pairwise_predictions`, :func:`predict_pairwise`).

Which pairs are matched is ``frontends/pair_selection.py``; a robot pose that disagrees with its
image, ``frontends/pose_check.py``.
"""

from calib3r_graph.frontends.pairwise.aggregation import aggregate, view_depths
from calib3r_graph.frontends.pairwise.features import extract_features, features_for
from calib3r_graph.frontends.pairwise.frontend import match_noise_px, pairwise_predictions, predict_pairwise
from calib3r_graph.frontends.pairwise.geometry import (guided_candidates, guided_matches, pair_geometries, refine_pose,
                                                       sampson_correction, two_view_geometry)
from calib3r_graph.frontends.pairwise.options import Features, PairGeometry, PairwiseOptions
from calib3r_graph.frontends.pairwise.robot import rescue_pairs, robot_consistent

__all__ = [
    "PairwiseOptions", "Features", "PairGeometry",
    "extract_features", "features_for",
    "two_view_geometry", "pair_geometries", "guided_matches", "guided_candidates", "refine_pose",
    "sampson_correction",
    "robot_consistent", "rescue_pairs",
    "view_depths", "aggregate",
    "match_noise_px", "pairwise_predictions", "predict_pairwise",
]
