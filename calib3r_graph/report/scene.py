"""The report's 3D view, in the robot base frame (metres): the metric point cloud (down-sampled,
coloured), every view's camera frustum, the robot's flange poses (red where the robot factor's
chi2 is flagged), and each camera's ee_T_cam axes with its 3-sigma position ellipsoid, drawn at
the first frame's flange and scaled up by a stated factor when it would be too small to see."""

import numpy as np
import plotly.graph_objects as go

from calib3r_graph.io.predictions import split_view_id

CAMERA_COLOURS = ["#e8710a", "#7b1fa2", "#00897b", "#c2185b", "#3949ab"]
AXIS_SCALE = [[0.0, "#d62728"], [0.5, "#2ca02c"], [1.0, "#1f77b4"]]  # x red, y green, z blue
MAX_CLOUD_POINTS = 40000
# The dense cloud (dense.ply) is decimated to this many points: ~3.2 MB of the page (float32 xyz and a
# uint16 palette index in base64, 21 bytes a point), so report.html stays well under 10 MB beside
# plotly.js (4.8 MB) and the sparse cloud (0.8 MB); solve_page.MAX_PAGE_BYTES guards the rest.
MAX_DENSE_POINTS = 150000


def dense_cloud_arrays(result_dir, max_points=MAX_DENSE_POINTS):
    """The dense cloud of ``result_dir/dense.ply`` as :func:`cloud_arrays` gives it, or None without one."""
    from pathlib import Path

    path = Path(result_dir) / "dense.ply"
    if not path.is_file():
        return None
    from calib3r_graph.dense.fuse import read_dense_ply

    d = read_dense_ply(path)
    return cloud_arrays(d["points"], d["colors"], max_points=max_points)


def cloud_arrays(points, colours, max_points=MAX_CLOUD_POINTS, seed=0):
    """Within 10 % of the 1-99 % percentile box per axis, a random subset of at most ``max_points``:
    float32 xyz (rounded to 0.1 mm) and its colours as :func:`palette_colours` gives them.

    Where the cloud has no image colours (all one grey), colours is None: coloured by height instead."""
    points, colours = np.asarray(points, float), np.asarray(colours, float)
    if len(points) > 100:  # stray points (depth smeared across edges) would dwarf the scene
        lo, hi = np.percentile(points, [1, 99], axis=0)
        keep = np.all((points >= lo - 0.1 * (hi - lo)) & (points <= hi + 0.1 * (hi - lo)), axis=1)
        points, colours = points[keep], colours[keep]
    if len(points) > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(len(points), max_points, replace=False))
        points, colours = points[keep], colours[keep]
    xyz = np.round(points, 4).astype(np.float32)
    if len(colours) and np.ptp(colours, axis=0).max() < 1e-6:
        return xyz, None
    return xyz, palette_colours(colours)


def palette_colours(colours, bits=4):
    """RGB in [0, 1] (N, 3) as (index (N,) uint16, palette ['#rrggbb', ...]): each channel rounded to
    ``bits`` bits (16 levels: at most 8/255 off), the palette holding the colours that occur.

    A point then costs the page 2.7 bytes (a uint16 in base64) instead of an 11-byte '"#rrggbb", '
    string, and plotly validates one array instead of a string per point (14 s for 175 k points)."""
    levels = (1 << bits) - 1
    q = np.clip(np.round(np.asarray(colours, float) * levels), 0, levels).astype(np.int64)
    code = (q[:, 0] << (2 * bits)) | (q[:, 1] << bits) | q[:, 2]
    used, index = np.unique(code, return_inverse=True)
    rgb = np.round(np.stack([used >> (2 * bits), (used >> bits) & levels, used & levels], 1) * 255 / levels)
    return index.ravel().astype(np.uint16), [f"#{r:02x}{g:02x}{b:02x}" for r, g, b in rgb.astype(int)]


def cloud_marker(xyz, colours, size) -> dict:
    """A Scatter3d marker: the palette colours of :func:`cloud_arrays`, or height where there are none."""
    if colours is None:
        return dict(size=size, color=xyz[:, 2], colorscale="Viridis")
    index, palette = colours
    n = len(palette)
    scale = [[i / max(n - 1, 1), c] for i, c in enumerate(palette)] if n > 1 else [[0, palette[0]], [1, palette[0]]]
    return dict(size=size, color=index, colorscale=scale, cmin=0, cmax=max(n - 1, 1), showscale=False)


def _segments(starts, ends):
    """(x, y, z) lists of line segments separated by None, for one Scatter3d trace."""
    xyz = [[], [], []]
    for a, b in zip(starts, ends):
        for k in range(3):
            xyz[k] += [float(a[k]), float(b[k]), None]
    return xyz


def _axes_trace(poses, length, name, width=4, showlegend=True, legendgroup=None):
    """Red/green/blue x/y/z axes of every pose (Pose3), as one trace."""
    starts, ends, colour = [], [], []
    for T in poses:
        R, t = T.rotation().matrix(), T.translation()
        for k in range(3):
            starts.append(t)
            ends.append(t + length * R[:, k])
            colour += [k, k, k]
    x, y, z = _segments(starts, ends)
    return go.Scatter3d(x=x, y=y, z=z, mode="lines", name=name, legendgroup=legendgroup, showlegend=showlegend,
                        hoverinfo="skip",
                        line=dict(width=width, color=colour, colorscale=AXIS_SCALE, cmin=0, cmax=2))


def frustum_lines(T, K, width, height, depth):
    """Segments of a camera frustum (apex at the centre, image rectangle at ``depth``)."""
    corners = np.array([[0, 0, 1], [width, 0, 1], [width, height, 1], [0, height, 1]], float)
    rays = corners @ np.linalg.inv(K).T
    R, c = T.rotation().matrix(), T.translation()
    far = (rays * depth) @ R.T + c
    starts = [c] * 4 + [far[i] for i in range(4)]
    ends = [far[i] for i in range(4)] + [far[(i + 1) % 4] for i in range(4)]
    return starts, ends


def nice_factor(ratio: float) -> int:
    """The largest of 1, 2, 5, 10, 20, 50, ... not above ``ratio`` (at least 1)."""
    if not np.isfinite(ratio) or ratio <= 1:
        return 1
    exp = int(np.floor(np.log10(ratio)))
    for m in (5, 2, 1):
        if m * 10**exp <= ratio:
            return m * 10**exp
    return 10**exp


def ellipsoid_mesh(centre, cov, factor, n_u=24, n_v=12):
    """Vertices and triangles of the 3-sigma ellipsoid of a 3x3 covariance, scaled by ``factor``."""
    lam, V = np.linalg.eigh(cov)
    radii = 3 * np.sqrt(np.maximum(lam, 0)) * factor
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n_u, endpoint=False), np.linspace(0, np.pi, n_v))
    sphere = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)], -1).reshape(-1, 3)
    pts = (sphere * radii) @ V.T + centre
    tri = []
    for i in range(n_v - 1):
        for j in range(n_u):
            a, b = i * n_u + j, i * n_u + (j + 1) % n_u
            tri += [(a, b, a + n_u), (b, b + n_u, a + n_u)]
    return pts, np.array(tri)


def scene_figure(sol, base_T_ee, view_grids, position_cov_ee, robot_rows, cloud=None, cloud_colours=None, dense=None):
    """The 3D figure. ``view_grids``: view -> (K, width, height) of the grid the view's depth lives on;
    ``position_cov_ee``: camera -> 3x3 covariance of ee_T_cam's translation in the ee frame (m^2);
    ``robot_rows``: from :func:`~calib3r_graph.report.residuals.robot_pose_residuals`; ``dense``: (xyz,
    colours) of the dense cloud (:func:`dense_cloud_arrays`), shown instead of the sparse cloud, which
    stays in the legend (click it to show it)."""
    cams = list(sol.ee_T_cam)
    frames = sorted({split_view_id(v)[1] for v in sol.base_T_cam})
    centres = np.array([T.translation() for T in sol.base_T_cam.values()]
                       + [base_T_ee[f].translation() for f in frames])
    extent = float(np.linalg.norm(np.ptp(centres, axis=0))) if len(centres) > 1 else 0.5
    shown = dense[0] if dense is not None and len(dense[0]) else cloud
    if shown is not None and len(shown):
        extent = max(extent, float(np.linalg.norm(np.percentile(shown, 95, 0) - np.percentile(shown, 5, 0))))
    size = max(0.06 * extent, 0.01)
    traces = []
    has_dense = dense is not None and len(dense[0]) > 0
    if cloud is not None and len(cloud):
        traces.append(go.Scatter3d(x=cloud[:, 0], y=cloud[:, 1], z=cloud[:, 2], mode="markers",
                                   marker=cloud_marker(cloud, cloud_colours, 1.5),
                                   name=("sparse " if has_dense else "") + f"point cloud ({len(cloud)} points)",
                                   hoverinfo="skip", visible="legendonly" if has_dense else True))
    if has_dense:
        xyz, colours = dense
        traces.append(go.Scatter3d(x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2], mode="markers",
                                   marker=cloud_marker(xyz, colours, 1.2),
                                   name=f"dense cloud ({len(xyz)} points, dense.ply decimated)", hoverinfo="skip"))
    for j, c in enumerate(cams):
        views = sorted(v for v in sol.base_T_cam if split_view_id(v)[0] == c)
        starts, ends, tips = [], [], []
        for v in views:
            K, w, h = view_grids[v]
            s, e = frustum_lines(sol.base_T_cam[v], K, w, h, size)
            starts += s
            ends += e
            tips.append(sol.base_T_cam[v].translation())
        x, y, z = _segments(starts, ends)
        colour = CAMERA_COLOURS[j % len(CAMERA_COLOURS)]
        traces.append(go.Scatter3d(x=x, y=y, z=z, mode="lines", line=dict(color=colour, width=3),
                                   name=f"{c} frustums ({len(views)} views)", legendgroup=c, hoverinfo="skip"))
        tips = np.array(tips)
        traces.append(go.Scatter3d(x=tips[:, 0], y=tips[:, 1], z=tips[:, 2], mode="markers", legendgroup=c,
                                   marker=dict(size=3, color=colour), name=f"{c} camera centres", showlegend=False,
                                   text=views, hovertemplate="%{text}<extra></extra>"))
    flange = [base_T_ee[f] for f in frames]
    by_frame = {r["frame"]: r for r in robot_rows}
    pos = np.array([T.translation() for T in flange])
    flagged = [by_frame.get(f, {}).get("flagged", False) for f in frames]
    text = [f"frame {f}<br>robot residual {by_frame[f]['translation_norm_mm']:.2f} mm, "
            f"{by_frame[f]['rotation_norm_deg']:.3f}°<br>χ² {by_frame[f]['chi2']:.1f}"
            + (" (flagged)" if by_frame[f]["flagged"] else "") if f in by_frame else f"frame {f}" for f in frames]
    traces.append(go.Scatter3d(x=pos[:, 0], y=pos[:, 1], z=pos[:, 2], mode="markers", name="flange poses (robot)",
                               legendgroup="flange", text=text, hovertemplate="%{text}<extra></extra>",
                               marker=dict(size=[7 if b else 4 for b in flagged],
                                           color=["#d62728" if b else "#333333" for b in flagged])))
    traces.append(_axes_trace(flange, 0.7 * size, "flange axes", width=3, showlegend=False, legendgroup="flange"))
    f0 = frames[0]
    for j, c in enumerate(cams):
        T = base_T_ee[f0].compose(sol.ee_T_cam[c])
        traces.append(_axes_trace([T], 1.5 * size, f"{c} ee_T_cam axes (at frame {f0})", width=7))
        cov = position_cov_ee.get(c)
        if cov is None:
            continue
        R = base_T_ee[f0].rotation().matrix()
        cov_base = R @ cov @ R.T
        semi = 3 * np.sqrt(max(np.linalg.eigvalsh(cov_base)[-1], 1e-18))
        factor = nice_factor(0.8 * size / semi)
        pts, tri = ellipsoid_mesh(T.translation(), cov_base, factor)
        label = f"{c} 3σ position ellipsoid" + (f" ×{factor}" if factor > 1 else "")
        traces.append(go.Mesh3d(x=pts[:, 0], y=pts[:, 1], z=pts[:, 2], i=tri[:, 0], j=tri[:, 1], k=tri[:, 2],
                                color=CAMERA_COLOURS[j % len(CAMERA_COLOURS)], opacity=0.45, name=label,
                                showlegend=True,
                                hovertemplate=f"{label}: largest 3σ {semi * 1e3:.2f} mm<extra></extra>"))
    fig = go.Figure(traces)
    fig.update_layout(height=720, margin=dict(l=0, r=0, t=30, b=0), template="plotly_white",
                      title=dict(text="robot base frame (m)", x=0.5, font=dict(size=13)),
                      legend=dict(x=0.01, y=0.98, bgcolor="rgba(255,255,255,0.8)"),
                      scene=dict(aspectmode="data", xaxis_title="x (m)", yaxis_title="y (m)", zaxis_title="z (m)",
                                 camera=dict(eye=dict(x=1.4, y=-1.4, z=0.9))))
    return fig
