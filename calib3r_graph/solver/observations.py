"""From predictions to the per-pair arrays the factors consume.

Each match is lifted to a 3D point in each view's camera at unit depth scale,
``d(u) * K^-1 [u, v, 1]``, with depth sampled bilinearly (only where all four
neighbours are valid, so points never bridge a depth edge). Dense matches are
redundant: at most ``max_matches_per_pair`` are kept per pair, drawn with
probability proportional to confidence.
"""

from dataclasses import dataclass

import numpy as np

from calib3r_graph.io.predictions import Predictions
from factors.match3d import depth_correction_basis


@dataclass
class PairObservations:
    view_a: str
    view_b: str
    uv_a: np.ndarray  # (N, 2) network-grid pixels
    uv_b: np.ndarray
    pts_a: np.ndarray  # (N, 3) d_a * ray_a, camera a, frontend depth units
    pts_b: np.ndarray  # (N, 3)
    weight: np.ndarray  # (N,) confidence weight, median 1
    basis_a: np.ndarray  # (N, K) depth-correction basis at uv_a (factors.match3d)
    basis_b: np.ndarray

    def __len__(self):
        return len(self.uv_a)

    def subset(self, keep):
        return PairObservations(self.view_a, self.view_b, self.uv_a[keep], self.uv_b[keep],
                                self.pts_a[keep], self.pts_b[keep], self.weight[keep],
                                self.basis_a[keep], self.basis_b[keep])


def bilinear_taps(shape, uv: np.ndarray) -> tuple:
    """Where :func:`sample_bilinear` samples an image of ``shape`` (h, w) at uv (N, 2): (inside,
    flat index of the top-left neighbour, row length, fx, fy), so that two images of one shape (a
    view's depth and confidence) are sampled with one computation of the taps."""
    h, w = shape
    x, y = uv[:, 0], uv[:, 1]
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = np.clip(x - x0, 0, 1), np.clip(y - y0, 0, 1)
    return inside, y0 * w + x0, w, fx, fy


def sample_taps(img: np.ndarray, taps: tuple):
    """Bilinear samples of img at :func:`bilinear_taps` and whether all four neighbours are > 0."""
    inside, i00, w, fx, fy = taps
    flat = img.ravel()
    c00, c01 = flat[i00], flat[i00 + 1]
    c10, c11 = flat[i00 + w], flat[i00 + w + 1]
    val = (c00 * (1 - fx) + c01 * fx) * (1 - fy) + (c10 * (1 - fx) + c11 * fx) * fy
    ok = inside & (c00 > 0) & (c01 > 0) & (c10 > 0) & (c11 > 0)
    return val, ok


def sample_bilinear(img: np.ndarray, uv: np.ndarray):
    """Bilinear samples of img at uv (N, 2) and whether all four neighbours are > 0."""
    return sample_taps(img, bilinear_taps(img.shape, uv))


def backproject(K: np.ndarray, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
    return np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(K).T * depth[:, None]


def build_observations(preds: Predictions, max_matches_per_pair: int = 3000, min_matches: int = 20,
                       seed: int = 0) -> list:
    rng = np.random.default_rng(seed)
    out = []
    for p in preds.pairs:
        va, vb = preds.views[p.view_a], preds.views[p.view_b]
        ta, tb = bilinear_taps(va.depth.shape, p.uv_a), bilinear_taps(vb.depth.shape, p.uv_b)
        d_a, ok_a = sample_taps(va.depth, ta)
        d_b, ok_b = sample_taps(vb.depth, tb)
        c_a, _ = sample_taps(va.conf, ta)  # a view's conf has its depth's shape (io/predictions checks it)
        c_b, _ = sample_taps(vb.conf, tb)
        w = p.conf * np.sqrt(np.maximum(c_a, 0) * np.maximum(c_b, 0))
        keep = np.flatnonzero(ok_a & ok_b & (w > 0))
        if len(keep) < min_matches:
            continue
        if len(keep) > max_matches_per_pair:
            prob = w[keep] / w[keep].sum()
            keep = np.sort(rng.choice(keep, size=max_matches_per_pair, replace=False, p=prob))
        w = w[keep] / np.median(w[keep])
        uv_a, uv_b = p.uv_a[keep], p.uv_b[keep]
        out.append(PairObservations(p.view_a, p.view_b, uv_a, uv_b,
                                    backproject(va.K, uv_a, d_a[keep]), backproject(vb.K, uv_b, d_b[keep]), w,
                                    depth_correction_basis(uv_a, va.depth.shape[1], va.depth.shape[0]),
                                    depth_correction_basis(uv_b, vb.depth.shape[1], vb.depth.shape[0])))
    return out
