"""Every public recording in ../shared/real end to end: import, each RGB frontend (colmap and
pairwise), solve, and compare --halves. Prints one table and writes it to bench/results/real.md, from
which docs/real-recordings.md's table and the README's headline figures are taken.

Per recording and method: the difference to the pattern reference (pattern-ba) in mm and
degrees, and in sigmas per ee axis (the method's total sigma combined with the reference's);
the halves' difference in sigmas of a difference; the reference's own halves repeatability and
the smallest tolerance it can judge (3x its repeatability); ours' total and model sigmas;
the times.

    .venv/bin/python bench/real.py [--real ../shared/real] [--work /tmp/calib3r-real]
                                   [--recordings rwhe_kuka_1,...] [--methods park,pattern-ba,...]
"""

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from calib3r_graph.cli import main  # noqa: E402
from calib3r_graph.evaluation.consistency import axis_differences  # noqa: E402
from calib3r_graph.importers import import_recording  # noqa: E402
from calib3r_graph.io.dataset import ee_T_cam_by_camera  # noqa: E402

# The boards, as each recording's README states them (inner corners); the importer finds the rest.
BOARDS = {"rwhe_kuka_1": (28, 17), "rwhe_kuka_2": (24, 17)}


def recording_format(src: Path) -> str | None:
    if (src / "RobotPosesVec.txt").exists():
        return "rwhe"
    if (src / "robot_cali.txt").exists():
        return "tabb"
    return None


def run_recording(src: Path, work: Path, methods: str, frontend: str) -> dict:
    fmt = recording_format(src)
    ds_dir, out = work / src.name, work / f"{src.name}-compare-{frontend}"
    times = {}
    if not (ds_dir / "dataset.yaml").exists():
        t = time.perf_counter()
        import_recording(fmt, src, ds_dir, BOARDS.get(src.name), progress=False)
        times["import"] = time.perf_counter() - t
    if not (ds_dir / "predictions" / frontend).is_dir():
        t = time.perf_counter()
        assert main(["-q", "predict", str(ds_dir), "--frontend", frontend]) == 0
        times["frontend"] = time.perf_counter() - t
    t = time.perf_counter()
    assert main(["-q", "solve", str(ds_dir), "--predictions", frontend, "--no-cloud", "--no-report",
                 "--out", str(work / f"{src.name}-solve-{frontend}")]) == 0
    times["solve"] = time.perf_counter() - t
    t = time.perf_counter()
    assert main(["-q", "compare", str(ds_dir), "--out", str(out), "--predictions", frontend, "--methods", methods,
                 "--halves", "--no-report"]) == 0
    times["compare --halves"] = time.perf_counter() - t
    cmp = json.loads((out / "comparison.json").read_text())
    halves = json.loads((out / "halves.json").read_text())
    calib = json.loads((work / f"{src.name}-solve-{frontend}" / "calibration.json").read_text())
    return {"name": src.name, "frontend": frontend, "comparison": cmp, "halves": halves, "calibration": calib,
            "times": times}


def table(results: list) -> str:
    lines = ["| recording | method | to reference: mm / deg | max σ to reference | halves: mm / deg | max σ halves "
             "| time (s) |", "|---|---|---|---|---|---|---|"]
    notes = []
    for r in results:
        cmp, halves = r["comparison"], r["halves"]
        ref_cams = ee_T_cam_by_camera(cmp["methods"]["pattern-ba"]["cameras"])
        first = r["frontend"] == results[0]["frontend"]
        for m, res in cmp["methods"].items():
            if not first and m != "calib3r-graph":
                continue  # the board and two-stage methods do not depend on the frontend: listed once
            label = f"{m} ({r['frontend']})" if m in ("calib3r-graph", "jcr-predictions") else m
            cams = ee_T_cam_by_camera(res["cameras"]) if res["status"] == "ok" else {}
            d = axis_differences(cams["cam0"], ref_cams["cam0"]) if "cam0" in cams and "cam0" in ref_cams else None
            to_ref = "–" if d is None or m == "pattern-ba" else \
                f"{sum(x * x for x in d[3:]) ** 0.5:.2f} / {sum(x * x for x in d[:3]) ** 0.5:.3f}"
            s_ref = cmp.get("in_sigmas", {}).get(m, {}).get("cam0", {}).get("max_ratio")
            h = halves["methods"].get(m, {}).get("cameras", {}).get("cam0")
            h_txt = f"{h['e_t_m'] * 1e3:.2f} / {h['e_theta_rad'] * 57.29578:.3f}" if h else "–"
            s_h = halves.get("in_sigmas", {}).get(m, {}).get("cam0", {}).get("max_ratio")
            lines.append(f"| {r['name']} | {label} | {to_ref} | {'–' if s_ref is None else f'{s_ref:.1f}σ'} | {h_txt} | "
                         f"{'–' if s_h is None else f'{s_h:.1f}σ'} | {res['seconds']:.1f} |")
        check = cmp.get("reference_validation", {})
        cal = r["calibration"]["cameras"]["cam0"]
        tot, mod = cal["sigma_ee_frame"], cal.get("sigma_ee_frame_model", {})
        sysm = r["calibration"]["solver"].get("systematic", {}).get("cam0", {})
        notes.append(f"- **{r['name']}**, {r['frontend']} frontend: {check.get('reason', 'no reference check')}. "
                     f"Ours' sigma (ee x, y, z): "
                     f"total {tot['x_mm']:.2f} / {tot['y_mm']:.2f} / {tot['z_mm']:.2f} mm, "
                     f"{tot['rx_deg']:.3f} / {tot['ry_deg']:.3f} / {tot['rz_deg']:.3f} deg; noise model alone "
                     f"{mod.get('x_mm', float('nan')):.2f} / {mod.get('y_mm', float('nan')):.2f} / "
                     f"{mod.get('z_mm', float('nan')):.2f} mm; robot error field "
                     f"{sysm.get('position_mm_per_m', float('nan')):.2f} mm/m and "
                     f"{sysm.get('position_mm_per_deg', float('nan')):.3f} mm/deg in position, "
                     f"{sysm.get('orientation_deg_per_m', float('nan')):.3f} deg/m and "
                     f"{sysm.get('orientation_deg_per_deg', float('nan')):.4f} deg/deg in orientation. Times: "
                     + ", ".join(f"{k} {v:.0f} s" for k, v in r["times"].items()) + ".")
    return "\n".join(lines) + "\n\n" + "\n".join(notes) + "\n"


def cli():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--real", default=str(ROOT.parent / "shared" / "real"))
    p.add_argument("--work", default="/tmp/calib3r-real", help="imports and frontend output are cached here")
    p.add_argument("--recordings", help="comma-separated names (default: every recording found)")
    p.add_argument("--methods", default="tsai,park,horaud,andreff,daniilidis,pattern-ba,jcr-colmap,jcr-predictions,"
                                        "calib3r-graph")
    p.add_argument("--frontends", default="colmap,pairwise",
                   help="RGB frontends for ours, in order; the other methods run with the first one only")
    args = p.parse_args()
    real, work = Path(args.real), Path(args.work)
    if not real.is_dir():
        sys.exit(f"bench/real.py: {real}: no such folder (the public recordings live in ../shared/real)")
    names = args.recordings.split(",") if args.recordings else sorted(d.name for d in real.iterdir()
                                                                      if d.is_dir() and recording_format(d))
    work.mkdir(parents=True, exist_ok=True)
    results = []
    frontends = args.frontends.split(",")
    for name in names:
        for k, frontend in enumerate(frontends):
            print(f"[bench/real] {name}, {frontend} frontend ...", file=sys.stderr, flush=True)
            results.append(run_recording(real / name, work, args.methods if k == 0 else "pattern-ba,calib3r-graph",
                                         frontend))
    text = table(results)
    out = ROOT / "bench" / "results" / "real.md"
    out.parent.mkdir(exist_ok=True)
    out.write_text(f"Command: `.venv/bin/python bench/real.py`\n\n{text}")
    (ROOT / "bench" / "results" / "real.json").write_text(json.dumps(results, indent=1))
    print(text)


if __name__ == "__main__":
    cli()
