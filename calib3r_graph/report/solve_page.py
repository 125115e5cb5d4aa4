"""report.html of ``solve``: the calibration, its uncertainty and warnings, the 3D scene, the robot
poses' residuals and the view pairs' residuals."""

from pathlib import Path

import gtsam
import numpy as np
import plotly.graph_objects as go
from plotly.subplots import make_subplots

from calib3r_graph.io.output import atomic_write_text
from calib3r_graph.io.results import AXES, covariance_in_ee_frame, point_cloud
from calib3r_graph.report.page import Page, esc, finite, fmt
from calib3r_graph.report.residuals import CHI2_6_99, pair_statistics, robot_pose_residuals
from calib3r_graph.report.scene import CAMERA_COLOURS, MAX_CLOUD_POINTS, cloud_arrays, dense_cloud_arrays, scene_figure

SIGMA_KEYS = ["x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg"]
KIND_PATTERN = {"total": "", "model": "/", "jackknife": "x"}


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
    cams = calibration["cameras"]
    robot = robot_pose_residuals(sol, ds.base_T_ee)
    pairs = pair_statistics(sol, preds, noise)
    st = sol.stats
    page = Page(f"calib3r-graph report: {ds.root.name}")
    page.add(f"<h1>calib3r-graph: {esc(ds.root.name)}</h1>")
    page.p(f"{ds.root} — predictions '{preds.name}', {st['views_used']} views, {st['pairs_used']} pairs, "
           f"{st['matches_used']} matches", cls="sub")
    for c, cal in cams.items():
        T = np.asarray(cal["T_ee_cam"])
        s = cal["sigma_ee_frame"]
        page.add(f"<p><b>{esc(c)}</b>: ee_T_cam t = [{', '.join(f'{v:.2f}' for v in T[:3, 3] * 1e3)}] mm, "
                 f"σ t = [{s['x_mm']:.2f} {s['y_mm']:.2f} {s['z_mm']:.2f}] mm, "
                 f"σ r = [{s['rx_deg']:.3f} {s['ry_deg']:.3f} {s['rz_deg']:.3f}]°</p>")
    _warnings(page, calibration, st, robot)

    page.h2("The scene in the robot's base frame", "scene")
    xyz, colours = _cloud(ds, preds, sol, cloud)
    grids = {v: (preds.views[v].K, preds.views[v].depth.shape[1], preds.views[v].depth.shape[0])
             for v in sol.base_T_cam}
    pos_cov = {c: covariance_in_ee_frame(sol.ee_T_cam[c], np.asarray(cal["covariance"]))[3:, 3:]
               for c, cal in cams.items()}
    page.add(page.figure(scene_figure(sol, ds.base_T_ee, grids, pos_cov, robot, xyz, colours, dense), "scene3d"))
    page.p("Drag to rotate, scroll to zoom, click a legend entry to hide it. Frustums show every view's "
           "base_T_cam; flange poses are the robot's base_T_ee, red where the robot factor is flagged; each "
           "camera's ee_T_cam is drawn at the first frame's flange, with its 3σ position ellipsoid scaled up "
           "by the factor in the legend. Axes: x red, y green, z blue.", cls="sub")

    _calibration_section(page, cams, st)
    _robot_section(page, robot, st)
    _pairs_section(page, pairs)
    page.h2("Summary (as printed)")
    page.add(f"<pre>{esc(summary)}</pre>")
    page.data(finite({"dataset": str(ds.root), "robot_poses": robot, "pairs": pairs,
                      "chi2_6_99": CHI2_6_99, "cloud_points": int(len(xyz)),
                      "dense_points": int(len(dense[0])) if dense is not None else 0}))
    return page.html()


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
