"""report.html of solve and compare: the numbers it shows, its size, and the page itself loaded in
headless Chromium (no JavaScript error, the expected traces in the 3D plot, a screenshot).

The browser tests skip where no Chromium is installed; ``scripts/setup.sh`` installs Debian's
``chromium`` package. Regenerate docs/report.md's screenshot with
``.venv/bin/python tests/test_report.py docs/report_sample.png``.
"""

import csv
import html
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from calib3r_graph.cli import main

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "datasets" / "sample"
MAX_BYTES = 10 * 1024 * 1024
CHI2_6_99 = 16.81

# Records every error (uncaught, unhandled rejection, console.error) from the first line on.
PROBE_HEAD = """<script>window.__errors = [];
window.addEventListener('error', function (e) { window.__errors.push('error: ' + (e.message || e)); });
window.addEventListener('unhandledrejection', function (e) { window.__errors.push('rejection: ' + e.reason); });
(function () { var ce = console.error; console.error = function () {
  window.__errors.push('console.error: ' + Array.prototype.join.call(arguments, ' '));
  ce.apply(console, arguments); }; })();
</script>"""
# After load, writes the errors and every plot's traces (name, type, points) into the DOM.
PROBE_TAIL = """<script>window.addEventListener('load', function () { setTimeout(function () {
  var out = {errors: window.__errors, plots: {}};
  document.querySelectorAll('.plotly-graph-div').forEach(function (gd) {
    out.plots[gd.id] = {canvases: gd.querySelectorAll('canvas').length,
                        no_webgl: gd.innerText.indexOf('WebGL is not supported') >= 0,
                        traces: (gd._fullData || []).map(function (t) {
                          return {name: t.name, type: t.type, n: (t.x && t.x.length) || 0}; })};
  });
  var pre = document.createElement('pre'); pre.id = '__probe'; pre.textContent = JSON.stringify(out);
  document.body.appendChild(pre); }, 3000); });
</script>"""


def chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        if shutil.which(name):
            return shutil.which(name)
    return None


def _chromium_run(url: str, profile: Path, *args) -> subprocess.CompletedProcess:
    # swiftshader: software WebGL, so the 3D plots render on a machine without a GPU
    cmd = [chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
           "--enable-unsafe-swiftshader", "--no-first-run", "--disable-dev-shm-usage", "--hide-scrollbars",
           f"--user-data-dir={profile}", "--virtual-time-budget=30000", *args, url]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300)


def load_in_browser(report: Path, work: Path) -> dict:
    """The report loaded in headless Chromium: {"errors": [...], "plots": {div id: {...}}}."""
    page = report.read_text()
    assert page.count('<meta charset="utf-8">') == 1 and page.count("</body>") == 1
    page = page.replace('<meta charset="utf-8">', '<meta charset="utf-8">' + PROBE_HEAD).replace(
        "</body>", PROBE_TAIL + "</body>")
    probe = work / "probe.html"
    probe.write_text(page)
    run = _chromium_run(probe.resolve().as_uri(), work / "chromium-profile", "--dump-dom")
    m = re.search(r'<pre id="__probe">(.*?)</pre>', run.stdout, re.S)
    assert m, f"no probe result in the DOM (rc {run.returncode}): {run.stderr[-2000:]}"
    return json.loads(html.unescape(m.group(1)))


def screenshot(report: Path, png: Path, work: Path, size="1280,900"):
    png.parent.mkdir(parents=True, exist_ok=True)
    _chromium_run(report.resolve().as_uri(), work / "chromium-shot", f"--window-size={size}",
                  f"--screenshot={png.resolve()}")
    assert png.is_file() and png.stat().st_size > 20000, f"no screenshot at {png}"


def report_data(report: Path) -> dict:
    m = re.search(r'<script type="application/json" id="report-data">(.*?)</script>', report.read_text(), re.S)
    return json.loads(m.group(1))


needs_chromium = pytest.mark.skipif(chromium() is None, reason="no chromium on PATH (scripts/setup.sh installs "
                                                                "Debian's chromium package)")


@pytest.fixture(scope="module")
def sample_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("report") / "sample"
    assert main(["-q", "solve", str(SAMPLE), "--out", str(out), "--no-cloud"]) == 0
    return out


def test_solve_report_numbers_and_size(sample_report):
    report = sample_report / "report.html"
    text = report.read_text()
    assert report.stat().st_size < MAX_BYTES
    assert not re.search(r"<script[^>]*\bsrc=", text), "must not load scripts from anywhere"
    assert len(re.findall(r"\* plotly\.js v\d", text)) == 1  # plotly.js inline, once
    calibration = json.loads((sample_report / "calibration.json").read_text())
    data = report_data(report)
    assert [r["frame"] for r in data["robot_poses"]] == [f"{i:04d}" for i in range(8)]
    assert [r["view"] for r in data["robot_poses"]] == [f"cam0/{i:04d}" for i in range(8)]  # reference camera
    assert not any(r["flagged"] for r in data["robot_poses"])  # the simulator's robot noise is what we assume
    assert all(0.05 < r["translation_norm_mm"] < 1.0 and r["chi2"] < CHI2_6_99 for r in data["robot_poses"])
    assert len(data["pairs"]) == calibration["solver"]["pairs_used"] == 56
    inliers = sum(p["inliers"] for p in data["pairs"])
    assert abs(inliers - calibration["solver"]["matches_used"]) <= 0.01 * inliers
    assert sum(p["matches"] for p in data["pairs"]) == calibration["solver"]["matches_total"]
    assert all(1.0 < p["median_residual_mm"] < 10.0 for p in data["pairs"])
    assert data["cloud_points"] == 40000  # --no-cloud still shows a (lighter) cloud
    gain = calibration["solver"]["systematic_error_gain"]["mm_per_mm"]
    assert round(gain, 1) == 2.8 and f"by about {gain:.1f} mm" in text  # the gain, in the summary's words
    assert "No observability warnings" in text and calibration["observability"] == []
    for cam in ("cam0", "cam1"):
        corr = calibration["cameras"][cam]["strongest_correlations"][0]
        assert f"Strongest correlations: {corr['axes'][0]}-{corr['axes'][1]} {corr['rho']:+.2f}" in text
    assert text.count("<td>σ total</td>") == 2


def test_no_report_flag(tmp_path):
    assert main(["-q", "solve", str(SAMPLE), "--out", str(tmp_path / "o"), "--no-cloud", "--no-report"]) == 0
    assert (tmp_path / "o" / "calibration.json").is_file()
    assert not (tmp_path / "o" / "report.html").exists()


@needs_chromium
def test_solve_report_in_chromium(sample_report, tmp_path):
    probe = load_in_browser(sample_report / "report.html", tmp_path)
    assert probe["errors"] == []
    scene = probe["plots"]["scene3d"]
    assert scene["canvases"] > 0 and not scene["no_webgl"]
    traces = {t["name"]: t for t in scene["traces"]}
    assert traces["point cloud (40000 points)"]["n"] == 40000
    for cam in ("cam0", "cam1"):
        assert traces[f"{cam} frustums (8 views)"]["n"] == 8 * 8 * 3  # 8 segments per frustum, 3 entries each
        assert traces[f"{cam} ee_T_cam axes (at frame 0000)"]["n"] == 3 * 3
        ellipsoid = [n for n in traces if n.startswith(f"{cam} 3σ position ellipsoid ×")]
        assert len(ellipsoid) == 1 and traces[ellipsoid[0]]["type"] == "mesh3d"
    assert traces["flange poses (robot)"]["n"] == 8
    assert traces["flange axes"]["n"] == 8 * 3 * 3
    assert {"sigmas", "robot-residuals", "pairs-heatmap"} <= set(probe["plots"])
    screenshot(sample_report / "report.html", tmp_path / "report.png", tmp_path)


def test_perturbed_robot_pose_is_flagged(sample_copy, tmp_path):
    path = sample_copy / "robot_poses.csv"
    rows = list(csv.reader(path.open()))
    for r in rows[1:]:
        if r[0] == "0003":
            r[1] = f"{float(r[1]) + 0.005:.9f}"  # 5 mm along base x: 25 sigma of the nominal robot noise
    with path.open("w") as f:
        csv.writer(f, lineterminator="\n").writerows(rows)
    assert main(["-q", "solve", str(sample_copy), "--out", str(tmp_path / "o"), "--no-cloud"]) == 0
    report = tmp_path / "o" / "report.html"
    data = report_data(report)
    flagged = [r for r in data["robot_poses"] if r["flagged"]]
    assert [r["frame"] for r in flagged] == ["0003"]
    assert flagged[0]["chi2"] > 1.5 * CHI2_6_99 and flagged[0]["translation_norm_mm"] > 1.5
    assert "robot pose(s) 0003" in report.read_text()


def test_solve_report_shows_model_and_jackknife_sigmas():
    """With the jackknife (the default below 15 poses), and with calibration.json's noise-model-only covariance beside the total one,
    the calibration table shows all three sigmas and the jackknife ratios."""
    import numpy as np

    from calib3r_graph.io.dataset import load_dataset
    from calib3r_graph.io.predictions import load_predictions
    from calib3r_graph.io.results import calibration_json, summary_text, uncertainty_report
    from calib3r_graph.report import solve_report_html
    from calib3r_graph.solver.graph import NoiseOptions
    from calib3r_graph.solver.solve import SolveOptions, solve

    ds = load_dataset(SAMPLE)
    preds = load_predictions(ds.root, "sim", ds.cameras, set(ds.frames))
    opt = SolveOptions(noise=NoiseOptions(pixel_sigma_px=float(preds.info.get("match_noise_px", 1.0))),
                       progress=False)
    sol = solve(ds, preds, opt)
    assert "jackknife" in sol.stats  # 8 poses, below JACKKNIFE_BELOW: solve runs it by default
    calibration = calibration_json(sol, preds.name)
    for c, cam in calibration["cameras"].items():  # a model-only covariance of half the total sigma
        if "sigma_ee_frame_model" not in cam:
            cam["covariance_model"] = (0.25 * np.asarray(cam["covariance"])).tolist()
            cam["sigma_ee_frame_model"] = uncertainty_report(sol.ee_T_cam[c], 0.25 * np.asarray(cam["covariance"]))[
                "sigma_ee_frame"]
    page = solve_report_html(ds, preds, sol, calibration, summary_text(sol, ds, preds.name), opt.noise)
    table = page[page.index('id="calibration"'):page.index('id="robot"')]
    assert table.count("<td>σ total</td>") == 2 and table.count("<td>σ noise model only</td>") == 2
    assert table.count("σ jackknife (8 solves)") == 2 and table.count("jackknife / modelled") == 2
    model = calibration["cameras"]["cam0"]["sigma_ee_frame_model"]["z_mm"]
    assert f"<td>{model:.3f}</td>" in table
    ratio = sol.stats["jackknife"]["cam0"]["ratio_to_reported"][5]  # z, tangent order [rx ry rz x y z]
    assert f"<td>{ratio:.2f}</td>" in table


@pytest.fixture(scope="module")
def compare_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("compare")
    assert main(["-q", "compare", str(SAMPLE), "--out", str(out), "--methods", "tsai,calib3r-graph", "--halves",
                 "--views", "6", "--repeats", "1"]) == 0
    return out


def test_compare_report(compare_report):
    report = compare_report / "report.html"
    assert report.stat().st_size < MAX_BYTES
    data = report_data(report)
    assert data["methods"] == ["tsai", "calib3r-graph"] and data["reference"] == "ground truth"
    assert data["halves"] and data["sweep"]
    comparison = json.loads((compare_report / "comparison.json").read_text())
    for m in ("tsai", "calib3r-graph"):
        assert comparison["methods"][m]["status"] == "ok"
        assert set(data["errors"][m]) == {"cam0", "cam1"}
    assert data["errors"]["calib3r-graph"]["cam0"][0] < 2.0  # mm against ground truth
    text = report.read_text()
    assert text.count("<td>tsai</td>") == 2 and text.count("<td>calib3r-graph</td>") == 2  # methods and halves


@needs_chromium
def test_compare_report_in_chromium(compare_report, tmp_path):
    probe = load_in_browser(compare_report / "report.html", tmp_path)
    assert probe["errors"] == []
    plots = probe["plots"]
    assert set(plots) == {"compare-errors", "compare-positions", "compare-times", "compare-halves", "compare-sweep"}
    names = {t["name"] for t in plots["compare-positions"]["traces"]}
    assert {"tsai cam0", "calib3r-graph cam1", "ground truth"} <= names
    assert {t["name"] for t in plots["compare-sweep"]["traces"]} == {"tsai", "calib3r-graph"}


if __name__ == "__main__":  # regenerate docs/report.md's screenshot: python tests/test_report.py docs/report_sample.png
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        assert main(["-q", "solve", str(SAMPLE), "--out", str(tmp / "sample"), "--no-cloud"]) == 0
        screenshot(tmp / "sample" / "report.html", tmp / "shot.png", tmp, size="1280,1000")
        from PIL import Image

        Image.open(tmp / "shot.png").convert("RGB").quantize(128).save(sys.argv[1], optimize=True)  # a small PNG
