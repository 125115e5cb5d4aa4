"""RGB-D frontend: the sensor's registered depth is the canonical (metric) depth, SIFT gives
the matches. Confidence is 1 where the depth is valid and away from depth edges (sensors
smear there), lower near edges, 0 without depth; match confidence from the ratio test."""

import itertools
import logging

import cv2
import numpy as np
from scipy import ndimage
from tqdm import tqdm

from calib3r_graph.errors import InputError
from calib3r_graph.frontends.common import covisibility_edges, load_gray, match_verified, sift_features, undistort_maps
from calib3r_graph.io.predictions import PairMatches, ViewPrediction, save_predictions, view_id

log = logging.getLogger(__name__)


def load_depth_m(ds, camera, frame):
    path = ds.depth_path(camera.name, frame)
    if path is None:
        return None
    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None or d.ndim != 2:
        raise InputError(path, "unreadable depth image (expected single-channel uint16 PNG)")
    if d.shape != (camera.height, camera.width):
        raise InputError(path, f"depth is {d.shape[1]}x{d.shape[0]}, camera {camera.name} is "
                               f"{camera.width}x{camera.height}")
    scale = camera.depth_scale if camera.depth_scale is not None else 0.001
    return d.astype(np.float32) * scale


def depth_confidence(depth):
    valid = depth > 0
    gy, gx = np.gradient(depth)
    edge = (np.hypot(gx, gy) > 0.02 * np.maximum(depth, 1e-6)) & valid
    edge = ndimage.binary_dilation(edge, iterations=2)
    return np.where(valid, np.where(edge, 0.2, 1.0), 0.0).astype(np.float32)


def predict_rgbd(ds, name="rgbd", neighbours=5, n_features=4000, max_pairs=None, progress=True):
    views, feats, Ks = {}, {}, {}
    items = [(c, f) for c in ds.cameras.values() for f in ds.frames if ds.image_path(c.name, f)]
    if not items:
        raise InputError(ds.root / "images", "no images for any camera and frame in robot_poses.csv")
    for cam, frame in tqdm(items, desc="rgbd: features", disable=None if progress else True, leave=False):
        depth = load_depth_m(ds, cam, frame)
        if depth is None:
            log.warning("%s/%s: no depth image; view skipped", cam.name, frame)
            continue
        gray = load_gray(ds.image_path(cam.name, frame))
        maps = undistort_maps(cam)
        if maps is not None:  # predictions live on an undistorted pinhole grid with the same K
            gray = cv2.remap(gray, *maps, cv2.INTER_LINEAR)
            depth = cv2.remap(depth, *maps, cv2.INTER_NEAREST)
        vid = view_id(cam.name, frame)
        views[vid] = ViewPrediction(depth, depth_confidence(depth), cam.K)
        feats[vid] = sift_features(gray, n_features)
        Ks[vid] = cam.K
    ids = sorted(views)
    candidates = list(itertools.combinations(ids, 2))
    matches, scores = {}, {}
    for a, b in tqdm(candidates, desc="rgbd: matching", disable=None if progress else True, leave=False):
        m = match_verified(feats[a], feats[b], Ks[a], Ks[b])
        if m is not None:
            matches[(a, b)] = m
            scores[(a, b)] = len(m[0])
    edges = covisibility_edges(scores, ids, neighbours)
    pairs = [PairMatches(a, b, *matches[(a, b)]) for a, b in edges]
    if not pairs:
        raise InputError(ds.root / "images", "no two images share enough verified SIFT matches")
    save_predictions(ds.root, name, views, pairs,
                     {"source": "calib3r-graph rgbd (sensor depth + OpenCV SIFT, essential-matrix RANSAC)",
                      "metric_depth": True, "match_noise_px": 0.7, "views": len(views), "pairs": len(pairs)})
    log.info("rgbd frontend: %d views, %d pairs, %d matches", len(views), len(pairs), sum(len(p.uv_a) for p in pairs))
    return name
