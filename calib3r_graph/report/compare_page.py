"""report.html of ``compare``: every method in a table and in plots (errors, where each puts the
camera in the ee frame, run time), and the halves and the views sweep when they were run."""

from pathlib import Path

import numpy as np
import plotly.graph_objects as go
from plotly.subplots import make_subplots

from calib3r_graph.evaluation.compare import METHODS, errors_against
from calib3r_graph.io.dataset import ee_T_cam_by_camera
from calib3r_graph.report.page import Page, esc, finite, fmt

OURS = "calib3r-graph"
PALETTE = ["#4c72b0", "#55a868", "#8172b2", "#ccb974", "#64b5cd", "#8c8c8c", "#937860", "#da8bc3", "#d62728"]


def _colour(m):
    return PALETTE[METHODS.index(m) % len(PALETTE)] if m in METHODS else "#444444"


def compare_report_html(dataset, result, reference, reference_name, sweep=None, halves=None) -> str:
    """``reference``: {camera: Pose3} (ground truth or pattern-ba), ``reference_name`` None without one."""
    methods = result["methods"]
    errs = errors_against(result, reference) if reference_name else {m: {} for m in methods}
    cams = sorted({c for r in methods.values() for c in r["cameras"]})
    page = Page(f"calib3r-graph compare: {Path(dataset).name}")
    page.add(f"<h1>calib3r-graph compare: {esc(Path(dataset).name)}</h1>")
    page.p(f"{dataset} — {len(methods)} methods, "
           + (f"errors against {reference_name} (e_t in mm, e_θ in degrees)" if reference_name
              else "no ground truth and no pattern-ba result: no errors to show"), cls="sub")

    page.h2("Every method", "methods")
    header = ["method", "status", "time (s)"]
    for c in cams:
        header += [f"{c} e_t (mm)", f"{c} e_θ (°)", f"{c} own σ t x/y/z (mm)"]
    rows, classes = [], []
    for m, r in methods.items():
        row = [m, r["status"], fmt(r["seconds"], ".1f")]
        for c in cams:
            e = errs.get(m, {}).get(c)
            s = r["cameras"].get(c, {}).get("sigma_ee_frame")
            row += [fmt(e[0] * 1e3, ".2f") if e else "–", fmt(np.degrees(e[1]), ".3f") if e else "–",
                    f"{s['x_mm']:.2f} / {s['y_mm']:.2f} / {s['z_mm']:.2f}" if s else "–"]
        rows.append(row)
        classes.append("flagged" if r["status"] != "ok" else "")
    page.table(header, rows, classes)

    if reference_name and any(errs.values()):
        page.add(page.figure(_error_bars(errs, cams, reference_name), "compare-errors"))
        page.add(page.figure(_positions(methods, reference, cams, reference_name), "compare-positions"))
    page.add(page.figure(_times(methods), "compare-times"))
    if halves:
        _halves_section(page, halves)
    if sweep and sweep.get("rows"):
        page.h2("Views sweep: error against the number of robot poses", "sweep")
        page.add(page.figure(_sweep(sweep, reference_name), "compare-sweep"))
    page.data(finite({"dataset": str(dataset), "reference": reference_name, "methods": list(methods),
                      "errors": {m: {c: [e[0] * 1e3, float(np.degrees(e[1]))] for c, e in v.items()}
                                 for m, v in errs.items()},
                      "halves": bool(halves), "sweep": bool(sweep and sweep.get("rows"))}))
    return page.html()


def _error_bars(errs, cams, reference_name):
    fig = make_subplots(rows=1, cols=2, subplot_titles=[f"e_t (mm) against {reference_name}",
                                                        f"e_θ (°) against {reference_name}"])
    names = [m for m in errs if errs[m]]
    for j, c in enumerate(cams):
        for col, f in ((1, lambda e: e[0] * 1e3), (2, lambda e: np.degrees(e[1]))):
            y = [f(errs[m][c]) if c in errs[m] else None for m in names]
            fig.add_trace(go.Bar(x=names, y=y, name=c, legendgroup=c, showlegend=col == 1,
                                 marker_color=[("#d62728" if m == OURS else "#7f7f7f") for m in names],
                                 marker_pattern_shape=["", "/", "x", "."][j % 4], texttemplate="%{y:.3g}",
                                 textposition="outside"), 1, col)
    fig.update_yaxes(type="log")
    fig.update_layout(height=380, barmode="group", template="plotly_white", margin=dict(l=40, r=20, t=40, b=90))
    return fig


def _positions(methods, reference, cams, reference_name):
    """Each method's ee_T_cam translation minus the reference's, in the ee frame (mm), with its own 1σ."""
    fig = go.Figure()
    for m, r in methods.items():
        X = ee_T_cam_by_camera(r["cameras"])
        for c in cams:
            if c not in X or c not in reference:
                continue
            d = (X[c].translation() - reference[c].translation()) * 1e3
            s = r["cameras"][c].get("sigma_ee_frame")
            err = {k: dict(type="data", array=[s[f"{k}_mm"]], visible=True) for k in "xyz"} if s else {}
            fig.add_trace(go.Scatter3d(x=[d[0]], y=[d[1]], z=[d[2]], mode="markers", name=f"{m} {c}",
                                       marker=dict(size=7 if m == OURS else 5, color=_colour(m),
                                                   symbol=["circle", "diamond", "square"][cams.index(c) % 3]),
                                       error_x=err.get("x"), error_y=err.get("y"), error_z=err.get("z"),
                                       hovertemplate=f"{m} {c}<br>Δ = [%{{x:.2f}}, %{{y:.2f}}, %{{z:.2f}}] mm"
                                                     "<extra></extra>"))
    fig.add_trace(go.Scatter3d(x=[0], y=[0], z=[0], mode="markers", name=reference_name,
                               marker=dict(size=4, color="black", symbol="cross")))
    fig.update_layout(height=520, template="plotly_white", margin=dict(l=0, r=0, t=40, b=0),
                      title=dict(text=f"camera position against {reference_name}, ee frame (mm; bars: own 1σ)",
                                 font=dict(size=13)),
                      scene=dict(aspectmode="cube", xaxis_title="Δx (mm)", yaxis_title="Δy (mm)",
                                 zaxis_title="Δz (mm)"))
    return fig


def _times(methods):
    names = list(methods)
    fig = go.Figure(go.Bar(x=names, y=[methods[m]["seconds"] for m in names], texttemplate="%{y:.1f}",
                           textposition="outside", name="time",
                           marker_color=["#d62728" if m == OURS else "#7f7f7f" for m in names]))
    fig.update_layout(height=300, template="plotly_white", margin=dict(l=40, r=20, t=40, b=90),
                      title=dict(text="run time (s)", font=dict(size=13)))
    return fig


def _halves_section(page, halves):
    page.h2("Halves: each method on the first half of the frames against itself on the second", "halves")
    f1, f2 = halves["frames"]
    page.p(f"Frames {f1[0]}–{f1[-1]} against frames {f2[0]}–{f2[-1]}. A bias that every pose shares moves a "
           "result by an amount that depends on which poses were recorded; no sigma shows it, the halves can.")
    cams = sorted({c for r in halves["methods"].values() for c in r["cameras"]})
    rows = []
    for m, r in halves["methods"].items():
        row = [m]
        for c in cams:
            e = r["cameras"].get(c)
            row += [fmt(e["e_t_m"] * 1e3, ".2f"), fmt(np.degrees(e["e_theta_rad"]), ".3f")] if e else ["–", "–"]
        rows.append(row + [r["status"]])
    page.table(["method"] + [f"{c} {k}" for c in cams for k in ("e_t (mm)", "e_θ (°)")] + ["status"], rows)
    fig = make_subplots(rows=1, cols=2, subplot_titles=["halves apart: e_t (mm)", "halves apart: e_θ (°)"])
    names = [m for m, r in halves["methods"].items() if r["cameras"]]
    for j, c in enumerate(cams):
        for col, f in ((1, lambda e: e["e_t_m"] * 1e3), (2, lambda e: np.degrees(e["e_theta_rad"]))):
            fig.add_trace(go.Bar(x=names, y=[f(halves["methods"][m]["cameras"][c])
                                              if c in halves["methods"][m]["cameras"] else None for m in names],
                                 name=c, legendgroup=c, showlegend=col == 1, texttemplate="%{y:.3g}",
                                 textposition="outside",
                                 marker=dict(color=["#d62728" if m == OURS else "#7f7f7f" for m in names],
                                             pattern_shape=["", "/", "x", "."][j % 4])), 1, col)
    fig.update_yaxes(type="log")
    fig.update_layout(height=360, barmode="group", template="plotly_white", margin=dict(l=40, r=20, t=40, b=90))
    page.add(page.figure(fig, "compare-halves"))


def _sweep(sweep, reference_name):
    rows = [r for r in sweep["rows"] if r.get("e_t_m") is not None]  # a failed run is a row without errors
    methods = sorted({r["method"] for r in rows}, key=lambda m: METHODS.index(m) if m in METHODS else 99)
    fig = make_subplots(rows=1, cols=2, subplot_titles=[f"e_t (mm) against {reference_name}",
                                                        f"e_θ (°) against {reference_name}"])
    for m in methods:
        ns = sorted({r["views"] for r in rows if r["method"] == m})
        for col, f in ((1, lambda r: r["e_t_m"] * 1e3), (2, lambda r: np.degrees(r["e_theta_rad"]))):
            vals = [[f(r) for r in rows if r["method"] == m and r["views"] == n] for n in ns]
            fig.add_trace(go.Scatter(x=ns, y=[float(np.mean(v)) for v in vals], mode="lines+markers", name=m,
                                     legendgroup=m, showlegend=col == 1,
                                     error_y=dict(type="data", array=[float(np.std(v)) for v in vals]),
                                     line=dict(color=_colour(m), width=3 if m == OURS else 1.5)), 1, col)
    fig.update_yaxes(type="log")
    fig.update_xaxes(title_text="robot poses")
    fig.update_layout(height=380, template="plotly_white", margin=dict(l=40, r=20, t=40, b=40))
    return fig
