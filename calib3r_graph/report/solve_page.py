"""report.html of ``solve``: the calibration, its uncertainty and warnings, the 3D scene, the robot
poses' residuals and the view pairs' residuals. ``solve`` builds it from its Solution in memory;
``reconstruct`` rebuilds it from the result folder's files (:func:`write_result_report`) so that it
shows the new dense cloud."""

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import gtsam
import numpy as np
import plotly.graph_objects as go
from plotly.subplots import make_subplots

from calib3r_graph.errors import InputError
from calib3r_graph.io.output import atomic_write_text
from calib3r_graph.io.predictions import split_view_id
from calib3r_graph.io.results import AXES, covariance_in_ee_frame, point_cloud, read_views
from calib3r_graph.report.page import Page, esc, finite, fmt
from calib3r_graph.report.residuals import CHI2_6_99, pair_statistics, robot_pose_residuals
from calib3r_graph.report.scene import CAMERA_COLOURS, MAX_CLOUD_POINTS, cloud_arrays, dense_cloud_arrays, scene_figure

SIGMA_KEYS = ["x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg"]
KIND_PATTERN = {"total": "", "model": "/", "jackknife": "x"}
# Issue 23: report.html with the dense cloud stays under 10 MB; 0.2 MB below it for what a browser or
# a mail gateway counts differently. plotly.js alone is 4.8 MB (plotly 7.1).
MAX_PAGE_BYTES = 9_800_000
# Bytes of the page per dense point, measured with plotly 7.1 on a 134669-point cloud: three float32
# coordinates and a uint16 palette index in base64, with the '/' of base64 escaped in the HTML.
DENSE_BYTES_PER_POINT = 21


def solve_report_writer(ds, preds, sol, noise=None):
    """A ``write_results(..., extra=)`` callback: writes report.html into the staging folder."""
    def write(stage, calibration, summary, cloud=None):
        atomic_write_text(Path(stage) / "report.html",
                          solve_report_html(ds, preds, sol, calibration, summary, noise, cloud,
                                            dense_cloud_arrays(stage)))
    return write


def _direction(d) -> str:  # as the observability warnings write ee directions
    d = np.round(np.asarray(d, float) * np.sign(d[np.argmax(np.abs(d))]), 2) + 0.0
    return f"[{d[0]:.2f} {d[1]:.2f} {d[2]:.2f}]"


def _cloud(ds, preds, sol, cloud):
    if cloud is None:  # no reconstruction.ply this run: a lighter cloud, enough for the picture
        cloud = point_cloud(ds, preds, sol, max_points_per_view=max(1000, 3 * MAX_CLOUD_POINTS // len(sol.base_T_cam)))
    return cloud_arrays(np.asarray(cloud.points), np.asarray(cloud.colors))


def solve_report_html(ds, preds, sol, calibration, summary, noise=None, cloud=None, dense=None) -> str:
    """The page from the solve's Solution in memory (``solve``, ``solve --dense``)."""
    grids = {v: (preds.views[v].K, preds.views[v].depth.shape[1], preds.views[v].depth.shape[0])
             for v in sol.base_T_cam}
    return _report_html(ds, preds.name, sol, calibration, summary, pair_statistics(sol, preds, noise), grids,
                        _cloud(ds, preds, sol, cloud), dense, calibration.get("dense"))


@dataclass
class SavedSolve:
    """What the page needs of a Solution, read back from a result folder: poses (gtsam.Pose3), the
    solver's stats (calibration.json's "solver") and, from views.npz when present, each view's depth
    scale and correction (for the sparse cloud when reconstruction.ply is absent)."""

    base_T_cam: dict
    ee_T_cam: dict
    stats: dict
    depth_scale: dict = field(default_factory=dict)
    depth_correction: dict = field(default_factory=dict)


def _saved_pairs(report_path: Path):
    """The view pairs' rows of an earlier report.html (its report-data JSON), or None. They come from the
    solve's factor graph (observations and values), which only exists while ``solve`` runs."""
    if not report_path.is_file():
        return None
    m = re.search(r'<script type="application/json" id="report-data">(.*?)</script>', report_path.read_text(), re.S)
    try:
        return json.loads(m[1])["pairs"] if m else None
    except (ValueError, KeyError, TypeError):
        return None


def result_report_html(result_dir, ds) -> str:
    """The page rebuilt from a result folder's files (``reconstruct``): calibration.json, trajectory.csv,
    views.npz, reconstruction.ply, dense.ply / dense.json and summary.txt, with the dataset's robot
    poses and cameras; the view pairs' rows are carried over from the folder's earlier report.html."""
    from calib3r_graph.dense.views import read_result

    d = Path(result_dir)
    saved = read_result(d)  # one-line errors for a folder without a solve
    calibration = json.loads((d / "calibration.json").read_text())
    sol = SavedSolve({v: gtsam.Pose3(T) for v, T in saved.base_T_cam.items()},
                     {c: gtsam.Pose3(X) for c, X in saved.ee_T_cam.items()}, calibration.get("solver", {}))
    if (d / "views.npz").is_file():  # the poses at full precision (trajectory.csv rounds them to 1 nm)
        states = read_views(d / "views.npz")
        sol.base_T_cam = {v: states.base_T_cam.get(v, T) for v, T in sol.base_T_cam.items()}
        sol.depth_scale, sol.depth_correction = states.depth_scale, states.depth_correction
    sol.base_T_cam = {v: T for v, T in sol.base_T_cam.items()
                      if split_view_id(v)[0] in ds.cameras and split_view_id(v)[1] in ds.base_T_ee}
    if not sol.base_T_cam:
        raise InputError(d / "trajectory.csv", f"no solved view belongs to the dataset {ds.root}")
    # the frustums: each camera's own K and image (the same frustum as on any scaled grid of it)
    grids = {v: (ds.cameras[c].K, ds.cameras[c].width, ds.cameras[c].height)
             for v in sol.base_T_cam for c in [split_view_id(v)[0]]}
    summary_path, dense_json = d / "summary.txt", d / "dense.json"
    summary = summary_path.read_text() if summary_path.is_file() else ""
    figures = json.loads(dense_json.read_text()) if dense_json.is_file() else calibration.get("dense")
    return _report_html(ds, calibration.get("predictions") or "?", sol, calibration, summary,
                        _saved_pairs(d / "report.html"), grids, _saved_cloud(d, ds, sol, calibration),
                        dense_cloud_arrays(d), figures)


def _saved_cloud(d: Path, ds, sol: SavedSolve, calibration):
    """reconstruction.ply, or (``solve --no-cloud``) the predictions' cloud through views.npz; None
    when neither can be had."""
    path = d / "reconstruction.ply"
    if path.is_file():
        import open3d as o3d

        pcd = o3d.io.read_point_cloud(str(path))
        return cloud_arrays(np.asarray(pcd.points), np.asarray(pcd.colors))
    name = calibration.get("predictions")
    if not name or not sol.depth_scale or not (ds.root / "predictions" / name).is_dir():
        return None
    from calib3r_graph.io.predictions import load_predictions

    preds = load_predictions(ds.root, name, ds.cameras, set(ds.frames), skip_missing=True)
    poses = {v: T for v, T in sol.base_T_cam.items() if v in preds.views and v in sol.depth_scale}
    if not poses:
        return None
    return _cloud(ds, preds, SavedSolve(poses, sol.ee_T_cam, sol.stats, sol.depth_scale, sol.depth_correction),
                  None)


def write_result_report(result_dir, dataset_dir) -> Path:
    """``reconstruct``: replaces RESULT_DIR/report.html (atomically) by :func:`result_report_html`."""
    from calib3r_graph.io.dataset import load_dataset

    path = Path(result_dir) / "report.html"
    atomic_write_text(path, result_report_html(result_dir, load_dataset(dataset_dir, skip_missing=True)))
    return path


def _report_html(ds, predictions_name, sol, calibration, summary, pairs, grids, cloud, dense, dense_figures) -> str:
    """``sol``: a Solution or a :class:`SavedSolve` (base_T_cam, ee_T_cam, stats); ``pairs``: rows of
    :func:`pair_statistics`, None where unknown; ``cloud``: (xyz, colours) of the sparse cloud or None;
    ``dense``: :func:`dense_cloud_arrays` or None; ``dense_figures``: dense.json's figures or None.

    The page stays under MAX_PAGE_BYTES: where the rest of it (plotly.js, the sparse cloud, the pairs)
    leaves too little room for the dense cloud, the dense cloud is decimated further and the page rebuilt."""
    def build(dense_shown):
        return _page_html(ds, predictions_name, sol, calibration, summary, pairs, grids, cloud, dense_shown,
                          dense_figures)

    html = build(dense)
    size = len(html.encode())
    while dense is not None and size > MAX_PAGE_BYTES and len(dense[0]) > 1000:
        n = len(dense[0])
        keep = max(1000, int(n - 1.05 * (size - MAX_PAGE_BYTES) / DENSE_BYTES_PER_POINT))
        idx = np.sort(np.random.default_rng(0).choice(n, keep, replace=False))
        dense = (dense[0][idx], None if dense[1] is None else (dense[1][0][idx], dense[1][1]))
        html = build(dense)
        size = len(html.encode())
    return html


def _page_html(ds, predictions_name, sol, calibration, summary, pairs, grids, cloud, dense, dense_figures) -> str:
    cams = calibration["cameras"]
    robot = robot_pose_residuals(sol, ds.base_T_ee)
    st = sol.stats
    page = Page(f"calib3r-graph report: {ds.root.name}")
    page.add(f"<h1>calib3r-graph: {esc(ds.root.name)}</h1>")
    page.p(f"{ds.root} — predictions '{predictions_name}', {st['views_used']} views, {st['pairs_used']} pairs, "
           f"{st['matches_used']} matches", cls="sub")
    for c, cal in cams.items():
        T = np.asarray(cal["T_ee_cam"])
        s = cal["sigma_ee_frame"]
        page.add(f"<p><b>{esc(c)}</b>: ee_T_cam t = [{', '.join(f'{v:.2f}' for v in T[:3, 3] * 1e3)}] mm, "
                 f"σ t = [{s['x_mm']:.2f} {s['y_mm']:.2f} {s['z_mm']:.2f}] mm, "
                 f"σ r = [{s['rx_deg']:.3f} {s['ry_deg']:.3f} {s['rz_deg']:.3f}]°</p>")
    _warnings(page, calibration, st, robot)

    page.h2("The scene in the robot's base frame", "scene")
    xyz, colours = cloud if cloud is not None else (None, None)
    pos_cov = {c: covariance_in_ee_frame(sol.ee_T_cam[c], np.asarray(cal["covariance"]))[3:, 3:]
               for c, cal in cams.items() if c in sol.ee_T_cam}
    page.add(page.figure(scene_figure(sol, ds.base_T_ee, grids, pos_cov, robot, xyz, colours, dense), "scene3d"))
    page.p("Drag to rotate, scroll to zoom, click a legend entry to hide it. Frustums show every view's "
           "base_T_cam; flange poses are the robot's base_T_ee, red where the robot factor is flagged; each "
           "camera's ee_T_cam is drawn at the first frame's flange, with its 3σ position ellipsoid scaled up "
           "by the factor in the legend. Axes: x red, y green, z blue.", cls="sub")
    if dense is not None and dense_figures:
        page.p(_dense_caption(dense_figures, len(dense[0]), xyz is not None), cls="sub")

    _calibration_section(page, cams, st)
    _robot_section(page, robot, st)
    _pairs_section(page, pairs)
    page.h2("Summary (as printed)")
    page.add(f"<pre>{esc(summary)}</pre>")
    page.data(finite({"dataset": str(ds.root), "robot_poses": robot, "pairs": pairs,
                      "chi2_6_99": CHI2_6_99, "cloud_points": int(len(xyz)) if xyz is not None else 0,
                      "dense_points": int(len(dense[0])) if dense is not None else 0}))
    return page.html()


def _dense_caption(f: dict, shown: int, has_sparse: bool) -> str:
    d = f.get("disagreement", {})
    dis = (f"; cross-view surface disagreement under base_T_ee·ee_T_cam: median {d['median_mm']:.2f} mm, 90 % "
           f"{d['p90_mm']:.2f} mm" if d.get("median_mm") is not None else "")
    return (f"Dense cloud ({f['source']}, {f['views_used']} views): dense.ply's {f['points']} points at "
            f"{f['voxel_mm']:g} mm, {shown} shown{dis}."
            + (" The sparse cloud (reconstruction.ply) is in the legend: click it to show it." if has_sparse else ""))


def _warnings(page, calibration, st, robot):
    msgs = calibration.get("observability") or []
    for m in msgs:
        page.add(f'<div class="warn">! {esc(m)}</div>')
    if not msgs:
        page.p("No observability warnings.", cls="ok")
    gain = st.get("systematic_error_gain")
    if gain:
        page.p(f"Systematic-error gain: each mm of systematic error in the robot's or the camera's relative "
               f"translations moves the translation of ee_T_cam along ee direction {_direction(gain['ee_direction'])} "
               f"by about {gain['mm_per_mm']:.1f} mm, which no sigma shows (a warning above 5).")
    bad = [r["frame"] for r in robot if r["flagged"]]
    if bad:
        page.add(f'<div class="warn">! robot pose(s) {esc(", ".join(bad))}: the robot factor\'s χ² is above the '
                 f'99 % quantile of χ²(6) ({CHI2_6_99:.1f}); see <a href="#robot">the robot poses</a></div>')


def _calibration_section(page, cams, st):
    page.h2("The calibration", "calibration")
    jk = st.get("jackknife", {})
    for c, cal in cams.items():
        T = np.asarray(cal["T_ee_cam"])
        page.add(f"<p><b>{esc(c)}</b>: T_ee_cam (m), metric scale {cal['metric_scale']:.5g} ± "
                 f"{cal['metric_scale_sigma']:.2g} m per frontend depth unit</p>"
                 f"<pre>{esc(np.array2string(T, precision=6, suppress_small=True))}</pre>")
        kinds = [("σ total", cal["sigma_ee_frame"])]
        if cal.get("sigma_ee_frame_model"):
            kinds.append(("σ noise model only", cal["sigma_ee_frame_model"]))
        if c in jk:
            kinds.append((f"σ jackknife ({jk[c]['solves']} solves)", jk[c]["sigma_jackknife"]))
        rows = [[k] + [fmt(s[key], ".3f") for key in SIGMA_KEYS] for k, s in kinds]
        if c in jk:
            ratio = np.array(jk[c]["ratio_to_reported"])[[3, 4, 5, 0, 1, 2]]  # tangent order [r; t] -> the columns
            rows.append(["jackknife / modelled"] + [fmt(r, ".2f") for r in ratio])
        page.table(["ee frame", "x (mm)", "y (mm)", "z (mm)", "rx (°)", "ry (°)", "rz (°)"], rows)
        corr = "; ".join(f"{a['axes'][0]}-{a['axes'][1]} {a['rho']:+.2f}" for a in cal["strongest_correlations"])
        page.p(f"Strongest correlations: {corr}.")
        sysc = st.get("systematic", {}).get(c)
        if c in jk:
            page.p(f"σ total covers the spread of {jk[c]['solves']} leave-one-pose-out solves (the jackknife; "
                   "it runs by default below 15 robot poses, where the robot's error field is poorly measured "
                   "or not at all). The ratio row compares it with the modelled σ (noise model + field).")
        if sysc and sysc.get("measured") is False:
            page.p("The robot's error field is not measurable from so few poses.")
        elif sysc and "position_mm_per_m" in sysc:
            page.p(f"Systematic part of σ total: robot error field {sysc['position_mm_per_m']:.2f} mm/m and "
                   f"{sysc['position_mm_per_deg']:.3f} mm/° in position, {sysc['orientation_deg_per_m']:.3f} °/m and "
                   f"{sysc['orientation_deg_per_deg']:.4f} °/° in orientation ({sysc.get('model', '')}).")
    nc = st.get("noise_calibration", {})
    if nc.get("method", "off") != "off":
        page.p(f"Noise calibration: scene variance factor {nc['variance_factor']:.3g}, design effect "
               f"{nc['design_effect']:.2f} (matches per independent observation), robot variance factor "
               f"{nc['robot_variance_factor']:.3g}.")
    fig = make_subplots(rows=1, cols=2 + len(cams), column_widths=[0.22, 0.22] + [0.56 / len(cams)] * len(cams),
                        subplot_titles=["σ translation (mm)", "σ rotation (°)"] + [f"{c} correlation" for c in cams])
    for j, (c, cal) in enumerate(cams.items()):
        kinds = [("total", cal["sigma_ee_frame"])] + \
                ([("model", cal["sigma_ee_frame_model"])] if cal.get("sigma_ee_frame_model") else []) + \
                ([("jackknife", jk[c]["sigma_jackknife"])] if c in jk else [])
        for kind, s in kinds:
            for col, keys in ((1, SIGMA_KEYS[:3]), (2, SIGMA_KEYS[3:])):
                fig.add_trace(go.Bar(x=[k.split("_")[0] for k in keys], y=[s[k] for k in keys], name=f"{c} {kind}",
                                     legendgroup=f"{c} {kind}", showlegend=col == 1,
                                     marker=dict(color=CAMERA_COLOURS[j % len(CAMERA_COLOURS)],
                                                 pattern_shape=KIND_PATTERN[kind])), 1, col)
        C = covariance_in_ee_frame(gtsam.Pose3(np.asarray(cal["T_ee_cam"])), np.asarray(cal["covariance"]))
        sig = np.sqrt(np.maximum(np.diag(C), 1e-30))
        fig.add_trace(go.Heatmap(z=np.round(C / np.outer(sig, sig), 3), x=AXES, y=AXES, zmin=-1, zmax=1,
                                 colorscale="RdBu", reversescale=True, showscale=j == 0,
                                 texttemplate="%{z:.2f}", name=f"{c} correlation"), 1, 3 + j)
        fig.update_yaxes(autorange="reversed", row=1, col=3 + j)
    fig.update_layout(height=360, barmode="group", template="plotly_white", margin=dict(l=40, r=20, t=40, b=30),
                      legend=dict(orientation="h", y=-0.15))
    page.add(page.figure(fig, "sigmas"))


def _robot_section(page, robot, st):
    page.h2("Robot poses: the robot factor's residual", "robot")
    mm, deg = st["noise_calibration"]["robot_sigma_used"]
    page.p(f"Residual e = Log((base_T_ee · ee_T_cam)⁻¹ · base_T_cam) of each frame's reference view; χ² with 6 "
           f"dof under the calibrated robot noise ({mm:.3g} mm, {deg:.3g}°). Poses above the 99 % quantile "
           f"({CHI2_6_99:.1f}) are flagged in red.")
    frames = [r["frame"] for r in robot]
    colour = ["#d62728" if r["flagged"] else "#4c72b0" for r in robot]
    fig = make_subplots(rows=1, cols=3, subplot_titles=["χ² (6 dof)", "translation residual (mm)",
                                                         "rotation residual (°)"])
    fig.add_trace(go.Bar(x=frames, y=[r["chi2"] for r in robot], marker_color=colour, name="χ²"), 1, 1)
    fig.add_hline(y=CHI2_6_99, line_dash="dash", line_color="#d62728", row=1, col=1,
                  annotation_text="99 %", annotation_position="top left")
    fig.add_trace(go.Bar(x=frames, y=[r["translation_norm_mm"] for r in robot], marker_color=colour, name="mm"), 1, 2)
    fig.add_trace(go.Bar(x=frames, y=[r["rotation_norm_deg"] for r in robot], marker_color=colour, name="deg"), 1, 3)
    fig.update_xaxes(type="category", title_text="frame")
    fig.update_layout(height=320, showlegend=False, template="plotly_white", margin=dict(l=40, r=20, t=40, b=40))
    page.add(page.figure(fig, "robot-residuals"))
    rows = [[r["frame"], r["view"], fmt(r["translation_norm_mm"], ".3f"),
             " ".join(f"{v:+.3f}" for v in r["translation_mm"]), fmt(r["rotation_norm_deg"], ".4f"),
             " ".join(f"{v:+.4f}" for v in r["rotation_deg"]), fmt(r["chi2"], ".2f"), "flagged" if r["flagged"] else ""]
            for r in robot]
    page.table(["frame", "view", "|t| (mm)", "t (mm, camera)", "|r| (°)", "r (°, camera)", "χ²", ""], rows,
               ["flagged" if r["flagged"] else "" for r in robot])


def _pairs_section(page, pairs):
    page.h2("View pairs: matches, inliers, residuals", "pairs")
    if pairs is None:
        page.p("The view pairs' residuals come from the solve's factor graph and this result folder's "
               "earlier report.html did not hold them: run solve again for them.")
        return
    if not pairs:
        page.p("No view pairs.")
        return
    page.p("Inliers: within the solver's 99.9 % χ²(3) cut at the solution (Mahalanobis distance under the "
           "per-match noise, robust scale). Median: the metric 3D residual |P_a − a_T_b·P_b| of the inliers, in mm.")
    views = sorted({p["view_a"] for p in pairs} | {p["view_b"] for p in pairs})
    idx = {v: i for i, v in enumerate(views)}
    z = np.full((len(views), len(views)), np.nan)
    text = np.full(z.shape, "", dtype=object)
    for p in pairs:
        for a, b in ((p["view_a"], p["view_b"]), (p["view_b"], p["view_a"])):
            z[idx[a], idx[b]] = round(p["median_residual_mm"], 3)
            text[idx[a], idx[b]] = (f"{p['view_a']} – {p['view_b']}<br>{p['matches']} matches, {p['inliers']} "
                                    f"inliers<br>median residual {p['median_residual_mm']:.2f} mm")
    fig = go.Figure(go.Heatmap(z=z, x=views, y=views, text=text, hovertemplate="%{text}<extra></extra>",
                               colorscale="YlOrRd", colorbar=dict(title="median mm")))
    fig.update_yaxes(autorange="reversed")
    fig.update_layout(height=max(360, 14 * len(views) + 120), width=max(480, 14 * len(views) + 220),
                      template="plotly_white", margin=dict(l=80, r=20, t=30, b=80),
                      title=dict(text="median inlier residual per view pair (mm)", font=dict(size=13)))
    page.add(page.figure(fig, "pairs-heatmap"))
    rows = [[p["view_a"], p["view_b"], p["matches"], p["inliers"], f"{100 * p['inliers'] / max(p['matches'], 1):.1f}",
             fmt(p["median_residual_mm"], ".2f")] for p in pairs]
    page.add(f"<details><summary>table of the {len(pairs)} pairs</summary>")
    page.table(["view a", "view b", "matches", "inliers", "inliers (%)", "median residual (mm)"], rows)
    page.add("</details>")
