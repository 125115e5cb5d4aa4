"""Per-view dense depth from the solved poses: neighbour views chosen by overlap and baseline, each pair
rectified with its solved relative pose (``cv2.stereoRectify`` on the distorted images with the camera's
distortion) and matched with OpenCV's semi-global matcher; a pixel's depth is kept where the pairs with
two or more different neighbour views agree (geometric consistency), with the share that agree as its
confidence."""

import logging
import warnings
from dataclasses import dataclass

import cv2
import numpy as np

log = logging.getLogger(__name__)

# SGBM's sub-pixel disparity is good to about 0.25 px on textured images; two pairs' depths that differ
# by more than one pixel of disparity of the pair (4 sigma) come from different matches.
AGREE_DISPARITY_PX = 1.0
DISPARITY_SIGMA_PX = 0.25
# Triangulation angle (baseline over depth) the neighbours are chosen around: 0.2 rad (11 deg) makes
# one pixel of disparity about 1/(0.2 f) of the depth, while a 0.6 rad pair still looks alike to SGBM.
BASELINE_RATIO_BEST, BASELINE_RATIO_RANGE = 0.2, (0.04, 0.6)
# Rectification keeps the image when the baseline is away from the optical axis (epipole outside the
# image): at most cos(55 deg) of the baseline along either view's axis.
MAX_BASELINE_ALONG_AXIS = 0.57
# SGBM compares square windows: beyond about 40 deg between the optical axes the same surface looks
# too different (foreshortening) after rectification.
MAX_AXIS_ANGLE_DEG = 40.0
MAX_DISPARITIES = 256  # SGBM's time grows with the disparity range; wider ranges give up the nearest depths
REFINE_WINDOW, REFINE_ITERATIONS, REFINE_MAX_PX = 7, 3, 1.5  # see refine_disparity


@dataclass
class PairDepth:
    depth: np.ndarray  # (h, w) float32 on the reference view's pinhole grid, NaN where no match
    f_baseline: float  # rectified focal length (px) x baseline (m): depth precision z^2 / fB per px


def pixel_rays(K: np.ndarray, size: tuple) -> np.ndarray:
    """(h, w, 3) rays K^-1 [u, v, 1] of a pinhole grid."""
    w, h = size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    return np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T


def depth_ranges(views: dict, points: np.ndarray) -> tuple[dict, dict]:
    """Per view, the (near, far, working) depth of the scene points it sees (5-95 % of their depths,
    widened by 25 %; working: their 25th percentile, the near part a hand-eye camera looks at, since the
    room behind a workspace can hold most of a sparse cloud's points), and which of the points it sees
    (boolean over ``points``, for the overlap)."""
    ranges, seen = {}, {}
    for v, dv in views.items():
        T = np.linalg.inv(dv.base_T_cam)
        q = points @ T[:3, :3].T + T[:3, 3]
        z = q[:, 2]
        ok = z > 1e-3
        uv = q[ok, :2] / z[ok, None] @ dv.K[:2, :2].T + dv.K[:2, 2]
        inside = np.zeros(len(points), bool)
        inside[ok] = (uv[:, 0] >= 0) & (uv[:, 0] < dv.size[0]) & (uv[:, 1] >= 0) & (uv[:, 1] < dv.size[1])
        seen[v] = inside
        if inside.sum() >= 10:
            lo, work, hi = np.percentile(z[inside], [5, 25, 95])
            ranges[v] = (0.8 * lo, 1.25 * hi, work)
    return ranges, seen


def look_at_points(views: dict) -> np.ndarray:
    """Scene points where no sparse cloud is at hand: each view's image grid at the depth where the views'
    optical axes pass closest to one another (the point they all look at)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for dv in views.values():
        d = dv.base_T_cam[:3, 2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ dv.base_T_cam[:3, 3]
    target = np.linalg.lstsq(A, b, rcond=None)[0]
    pts = []
    for dv in views.values():
        z = max(float((target - dv.base_T_cam[:3, 3]) @ dv.base_T_cam[:3, 2]), 0.05)
        w, h = dv.size
        g = np.stack(np.meshgrid(np.linspace(0, w - 1, 12), np.linspace(0, h - 1, 9)), -1).reshape(-1, 2)
        rays = np.c_[g, np.ones(len(g))] @ np.linalg.inv(dv.K).T
        for s in (0.7, 1.0, 1.4):
            pts.append((rays * z * s) @ dv.base_T_cam[:3, :3].T + dv.base_T_cam[:3, 3])
    return np.concatenate(pts)


def choose_neighbours(views: dict, ranges: dict, seen: dict, n: int) -> dict:
    """Up to ``n`` neighbours per view: enough overlap (a quarter of the scene points it sees), a
    triangulation angle in BASELINE_RATIO_RANGE, a baseline that rectifies, and the same working grid
    size; ranked by overlap times closeness of the angle to BASELINE_RATIO_BEST (log-normal, 1 e-fold)."""
    out = {}
    for v, a in views.items():
        if v not in ranges:
            out[v] = []
            continue
        z = ranges[v][2]
        cands = []
        for u, b in views.items():
            if u == v or b.size != a.size or not seen[v].any():
                continue
            base = b.base_T_cam[:3, 3] - a.base_T_cam[:3, 3]
            dist = float(np.linalg.norm(base))
            ratio = dist / z
            if not BASELINE_RATIO_RANGE[0] <= ratio <= BASELINE_RATIO_RANGE[1]:
                continue
            along = max(abs(base @ a.base_T_cam[:3, 2]), abs(base @ b.base_T_cam[:3, 2])) / dist
            if along > MAX_BASELINE_ALONG_AXIS:
                continue
            if a.base_T_cam[:3, 2] @ b.base_T_cam[:3, 2] < np.cos(np.radians(MAX_AXIS_ANGLE_DEG)):
                continue
            overlap = float((seen[v] & seen[u]).sum() / seen[v].sum())
            if overlap < 0.25:
                continue
            cands.append((overlap * np.exp(-0.5 * np.log(ratio / BASELINE_RATIO_BEST) ** 2), u))
        out[v] = [u for _, u in sorted(cands, reverse=True)[:n]]
    return out


def _matcher(min_disp: int, num_disp: int) -> cv2.StereoSGBM:
    block = 5
    return cv2.StereoSGBM_create(minDisparity=min_disp, numDisparities=num_disp, blockSize=block,
                                 P1=8 * block * block, P2=32 * block * block, disp12MaxDiff=1,
                                 uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)


def refine_disparity(left: np.ndarray, right: np.ndarray, disp: np.ndarray) -> np.ndarray:
    """Sub-pixel refinement of SGBM's disparity by 1-D Lucas-Kanade on the rectified pair: each pixel's
    disparity moves to where ``left(x) = right(x - d)`` best over a REFINE_WINDOW window, with the right
    image warped by every pixel's own disparity (so a slanted surface's disparity gradient is kept).

    SGBM's smoothness penalties favour constant disparity along its paths: on the simulator's slanted
    table that biased a pair's disparity by -0.95 to +0.89 px (median 0.6 px, i.e. 1.5 mm at 0.5 m);
    after REFINE_ITERATIONS steps the bias was 0.05 px and the median error 0.22 px (measured, one pair).
    A pixel the refinement moves by more than REFINE_MAX_PX was not a match and is dropped."""
    A, B = left.astype(np.float32), right.astype(np.float32)
    h, w = A.shape
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    grad = cv2.Sobel(B, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    ok = np.isfinite(disp)
    d = np.where(ok, disp, 0).astype(np.float32)
    win = (REFINE_WINDOW, REFINE_WINDOW)
    for _ in range(REFINE_ITERATIONS):
        warped = cv2.remap(B, xs - d, ys, cv2.INTER_LINEAR)
        g = np.where(ok, cv2.remap(grad, xs - d, ys, cv2.INTER_LINEAR), 0)
        r = np.where(ok, A - warped, 0)
        num = cv2.boxFilter(g * r, -1, win, normalize=False)
        den = cv2.boxFilter(g * g, -1, win, normalize=False)
        d -= np.clip(num / np.maximum(den, 1e-6), -0.5, 0.5)  # right(x - d - e) ~ right(x - d) - g e
    # Each pixel's own disparity noise: the residual's noise (both images', measured as the MAD of the
    # last residuals) over the window's gradient energy. Where it exceeds DISPARITY_SIGMA_PX the window
    # has too little texture (a board's uniform squares, a white wall): SGBM only carried a depth over
    # it from the edges, and the same wrong depth comes back from every view, so no fusion averages it out.
    sigma_r = 1.4826 * float(np.median(np.abs(r[ok]))) if ok.any() else np.inf
    sigma_d = sigma_r / np.sqrt(np.maximum(den, 1e-12))
    d[~ok | (np.abs(d - np.where(ok, disp, 0)) > REFINE_MAX_PX) | (sigma_d > DISPARITY_SIGMA_PX)] = np.nan
    return d


def pair_depth(a, b, zrange: tuple, rays_a: np.ndarray, max_sigma_m: float = np.inf) -> PairDepth | None:
    """Depth of view ``a`` from the pair (a, b): rectified with the solved relative pose, SGBM, and the
    disparity sampled back onto a's pinhole grid. None when the pair cannot be rectified. The search
    stops at the depth where one pair's noise, z^2 DISPARITY_SIGMA_PX / fB, reaches 1.25 ``max_sigma_m``
    (consistent_depth drops what lies beyond)."""
    b_T_a = np.linalg.inv(b.base_T_cam) @ a.base_T_cam
    R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(a.K_raw, a.dist, b.K_raw, b.dist, a.size, b_T_a[:3, :3],
                                                b_T_a[:3, 3], flags=cv2.CALIB_ZERO_DISPARITY, alpha=-1)
    maps_a = cv2.initUndistortRectifyMap(a.K_raw, a.dist, R1, P1, a.size, cv2.CV_32FC1)
    maps_b = cv2.initUndistortRectifyMap(b.K_raw, b.dist, R2, P2, b.size, cv2.CV_32FC1)
    ra = cv2.remap(a.gray, *maps_a, cv2.INTER_LINEAR)
    rb = cv2.remap(b.gray, *maps_b, cv2.INTER_LINEAR)
    horizontal = abs(P2[0, 3]) >= abs(P2[1, 3])
    tx = P2[0, 3] if horizontal else P2[1, 3]
    f = P1[0, 0]
    if not np.isfinite(f) or f <= 0 or abs(tx) < 1e-9 or not np.all(np.isfinite(maps_a[0][::50, ::50])):
        return None
    fB = abs(tx)  # rectified f (px) x baseline (m)
    z_far = min(zrange[1], 1.25 * np.sqrt(max_sigma_m * fB / DISPARITY_SIGMA_PX))
    d_lo, d_hi = fB / z_far, fB / zrange[0]
    min_disp = int(np.floor(d_lo))
    num = int(np.clip(np.ceil((d_hi - min_disp) / 16) * 16, 16, MAX_DISPARITIES))
    if not horizontal:
        ra, rb = ra.T, rb.T
    flip = tx > 0  # b is left of a: mirror both so that a is the left image
    if flip:
        ra, rb = ra[:, ::-1], rb[:, ::-1]
    log.debug("pair %s-%s: fB %.2f, z %s, disparities %d + %d", a.vid, b.vid, fB, zrange, min_disp, num)
    # SGBM needs min + num disparities inside the image (with room for its block): a wider range gives up
    # the nearest depths, and a pair whose farthest useful depth already lies beyond is skipped
    num = min(num, (ra.shape[1] - 32 - min_disp) // 16 * 16)
    if num < 16:
        return None
    try:
        disp = _matcher(min_disp, num).compute(np.ascontiguousarray(ra), np.ascontiguousarray(rb))
    except cv2.error as e:  # a pair OpenCV cannot match is skipped, the view keeps its other pairs
        log.debug("pair %s-%s: SGBM failed (%s)", a.vid, b.vid, str(e).splitlines()[0])
        return None
    disp = disp.astype(np.float32) / 16.0
    # disparities at the ends of the searched range are where the matcher ran out of range, not matches
    disp[(disp < min_disp + 0.5) | (disp > min_disp + num - 1.5)] = np.nan
    disp = refine_disparity(ra, rb, disp)
    if flip:
        disp = disp[:, ::-1]
    if not horizontal:
        disp = disp.T
    disp = np.ascontiguousarray(disp)
    r = rays_a @ R1.T  # a's pixel rays in the rectified frame
    with np.errstate(divide="ignore", invalid="ignore"):
        mx = (f * r[..., 0] / r[..., 2] + P1[0, 2]).astype(np.float32)
        my = (P1[1, 1] * r[..., 1] / r[..., 2] + P1[1, 2]).astype(np.float32)
    d = cv2.remap(disp, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where((r[..., 2] > 0) & (d > 0), fB / d / r[..., 2], np.nan).astype(np.float32)
    return PairDepth(depth, fB)


def consistent_depth(estimates: list, max_sigma_m: float = np.inf, min_agree: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """One depth per pixel from the pairs' estimates: the median, then the precision-weighted mean
    (weight (fB)^2) of the estimates within AGREE_DISPARITY_PX of disparity of it; kept where at least
    ``min_agree`` pairs (so ``min_agree`` different neighbour views) agree and where the depth's own
    noise, z^2 DISPARITY_SIGMA_PX / fB of the agreeing pairs combined, is at most ``max_sigma_m`` (the
    fusion's voxel: a farther depth cannot be placed at that size, and the far room behind a workspace
    would otherwise fill the volume). Returns (depth with NaN where dropped, confidence = share of the
    pairs that agree)."""
    E = np.stack([e.depth for e in estimates])
    fB = np.array([e.f_baseline for e in estimates])[:, None, None]
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels: no pair matched them
        med = np.nanmedian(E, axis=0)
        tol = AGREE_DISPARITY_PX * med ** 2 / fB
        agree = np.abs(E - med) <= tol
        w = np.where(agree, fB ** 2, 0.0)
        n = agree.sum(0)
        depth = (np.nan_to_num(E) * w).sum(0) / w.sum(0)
        sigma = DISPARITY_SIGMA_PX * depth ** 2 / np.sqrt(w.sum(0))
    keep = (n >= min_agree) & (sigma <= max_sigma_m)
    return np.where(keep, depth, np.nan).astype(np.float32), np.where(keep, n / len(estimates), 0).astype(np.float32)
