"""The pairwise frontend's features, once per image (step 1 in ``frontend.py``): undistorted, downscaled
to ``max_side``, RootSIFT; cached on disk per image and options."""

from pathlib import Path

import cv2
import numpy as np

from calib3r_graph.errors import InputError
from calib3r_graph.frontends.common import load_gray, undistort_maps
from calib3r_graph.frontends.pairwise.options import (Features, PairwiseOptions, _digest, _image_key,
                                                      _map_with_progress, read_npz)
from calib3r_graph.io.output import atomic_savez
from calib3r_graph.io.predictions import split_view_id


def extract_features(ds, cam, frame, opt: PairwiseOptions) -> Features:
    gray = load_gray(ds.image_path(cam.name, frame))
    if gray.shape != (cam.height, cam.width):
        raise InputError(ds.image_path(cam.name, frame), f"image is {gray.shape[1]}x{gray.shape[0]}, camera "
                                                        f"{cam.name} is {cam.width}x{cam.height}")
    maps = undistort_maps(cam)
    if maps is not None:
        gray = cv2.remap(gray, *maps, cv2.INTER_LINEAR)
    s = min(1.0, opt.max_side / max(gray.shape))
    small = cv2.resize(gray, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s < 1 else gray
    sift = cv2.SIFT_create(nfeatures=opt.n_features, contrastThreshold=opt.contrast_threshold)
    kp, desc = sift.detectAndCompute(small, None)
    if desc is None or not kp:
        return Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32), np.zeros(0, np.int64))
    pts = np.array([k.pt for k in kp], dtype=np.float64)
    # small-image pixel centres -> full-resolution pixel centres (OpenCV: centre of pixel 0 at 0)
    uv = (pts + 0.5) / np.array([small.shape[1] / gray.shape[1], small.shape[0] / gray.shape[0]]) - 0.5
    desc = desc.astype(np.float32)
    desc /= np.maximum(desc.sum(1, keepdims=True), 1e-12)  # RootSIFT
    # at the precision the feature cache keeps (float16, features_for): a run that computes the
    # features and one that reads them back then match the same descriptors. Without it they differed
    # by up to 1.2e-4, and solve on tabb_ds1 from an empty cache and then from the cache by 0.49 sigma
    # (docs/frontends.md)
    desc = np.sqrt(desc).astype(np.float16).astype(np.float32)
    _, kp_id = np.unique(np.round(pts * 100).astype(np.int64), axis=0, return_inverse=True)
    return Features(uv, desc, kp_id.ravel())


def features_for(ds, views, opt: PairwiseOptions, cache_dir=None, progress=True, workers=2) -> dict:
    """{view: Features} for the given view ids, from the cache where present."""
    cache = Path(cache_dir) / "features" if cache_dir else None

    def one(vid):
        cam_name, frame = split_view_id(vid)
        cam = ds.cameras[cam_name]
        path = None
        if cache is not None:
            path = cache / f"{cam_name}_{frame}_{_digest([_image_key(ds, cam, frame), opt.feature_key()])}.npz"
            if path.is_file():
                z = read_npz(path)
                return vid, Features(z["uv"], z["desc"].astype(np.float32), z["kp_id"])
        f = extract_features(ds, cam, frame, opt)
        if path is not None:
            atomic_savez(path, uv=f.uv, desc=f.desc.astype(np.float16), kp_id=f.kp_id)
        return vid, f

    return _map_with_progress(one, views, "pairwise: features", progress, workers)
