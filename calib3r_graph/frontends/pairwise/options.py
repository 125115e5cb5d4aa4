"""The pairwise frontend's options (:class:`PairwiseOptions`), what its steps hand on (a view's
:class:`Features`, a pair's :class:`PairGeometry`), and the small helpers several steps share: the
on-disk cache's keys (:func:`_digest` of :func:`_image_key` and the options' keys) and a threaded map
with a progress bar."""

import hashlib
import json
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from tqdm import tqdm


@dataclass(frozen=True)
class PairwiseOptions:
    # features
    max_side: int = 1600  # long side of the image SIFT sees (px); keypoints are scaled back
    n_features: int = 4000
    contrast_threshold: float = 0.02  # OpenCV's default 0.04 is twice COLMAP's peak threshold
    # two-view geometry
    ratio: float = 0.8
    ransac_px: float = 1.0  # essential-matrix inlier threshold on the full-resolution grid
    min_inliers: int = 30
    max_reprojection_px: float = 2.0
    guided: bool = True  # second matching pass along the epipolar lines of the first pose
    # which pairs are matched (frontends/pair_selection.py): each view's best partners by the image
    # and the robot, 0 = every pair. 10 partners give each view more verified pairs than the 8
    # neighbours the matches keep (``neighbours``), after the pairs that do not verify.
    partners: int = 10
    more_rounds: int = 2  # rounds of further partners for weakly connected views
    # robot consistency (never ground truth: it only rejects pairs)
    angle_tol_deg: float = 1.0
    rotation_tol_deg: float = 1.0
    translation_tol_deg: float = 5.0
    rescue: bool = True  # robot-guided matching for the pairs of weakly connected views
    rescue_below: int = 6  # ... views with fewer usable pairs than this
    rescue_band_deg: float = 0.5  # half-width of the predicted epipolar band (angle at the camera)
    # aggregation
    min_pair_angle_deg: float = 0.5  # median triangulation angle below which a pair gives no depth
    min_shared: int = 8
    max_scale_mad: float = 0.05  # robust scatter (log) of a pair's depth ratios to the reference
    max_depth_spread: float = 0.05  # relative deviation from a keypoint's median depth
    min_view_points: int = 30
    neighbours: int = 8

    def feature_key(self) -> dict:
        return {"max_side": self.max_side, "n_features": self.n_features,
                "contrast_threshold": self.contrast_threshold, "v": 1}

    def pair_key(self) -> dict:
        # v3: pairs matched on the cache's float16 descriptors (extract_features); a v2 pair may have
        # been matched on the float32 ones of the run that made the cache
        return {"ratio": self.ratio, "ransac_px": self.ransac_px, "min_inliers": self.min_inliers,
                "max_reprojection_px": self.max_reprojection_px, "guided": self.guided, **self.feature_key(), "v": 3}


@dataclass
class Features:
    uv: np.ndarray  # (N, 2) float64, undistorted full-resolution pixels (OpenCV convention)
    desc: np.ndarray  # (N, 128) float32 RootSIFT, unit L2 norm
    kp_id: np.ndarray  # (N,) int: features at the same location share an id


@dataclass
class PairGeometry:
    view_a: str
    view_b: str
    ia: np.ndarray  # (n,) feature indices in a
    ib: np.ndarray  # (n,) feature indices in b
    depth_a: np.ndarray  # (n,) z in camera a, in the pair's unit (|t| = 1)
    depth_b: np.ndarray
    angle: np.ndarray  # (n,) triangulation angle, rad
    conf: np.ndarray  # (n,) 1 - distance ratio
    R: np.ndarray  # x_b = R x_a + t
    t: np.ndarray
    stats: dict = field(default_factory=dict)

    def __len__(self):
        return len(self.ia)


# ----------------------------------------------------------------------------- shared helpers


def _digest(obj) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _image_key(ds, cam, frame) -> dict:
    p = ds.image_path(cam.name, frame)
    st = p.stat()
    return {"image": str(p.resolve()), "size": st.st_size, "mtime": int(st.st_mtime), "params": list(cam.params),
            "w": cam.width, "h": cam.height}


# np.load parses each array's header with ast.literal_eval, and CPython 3.11's AST constructor keeps
# its recursion depth per interpreter, not per thread: two threads parsing at once can raise
# "SystemError: AST constructor recursion depth mismatch" (python/cpython#106905). It ended a
# benchmark here, reading cached features on the frontend's two threads (2026-12-07; the first time
# in the project's many cached runs, and 40,000 reads on two threads in a loop did not repeat it).
# The cache reads take this lock; the work between them stays parallel.
_NPZ_LOCK = threading.Lock()


def read_npz(path) -> dict:
    """{name: array} of an .npz file, read whole under a lock shared by the frontend's threads."""
    with _NPZ_LOCK, np.load(path) as z:
        return {k: z[k] for k in z.files}


def _map_with_progress(one, items, desc, progress, workers) -> dict:
    """dict(one(item) for item in items), on ``workers`` threads, with a progress bar."""
    out = {}
    with ThreadPoolExecutor(max(1, workers)) as pool:
        for key, value in tqdm(pool.map(one, items), total=len(items), desc=desc,
                               disable=None if progress else True, leave=False):
            out[key] = value
    return out
