"""The camera model's share of the total sigma (solver/camera_model.py), measured: solve with the
intrinsics' stated 1-sigma, then again with a parameter moved by that sigma, and compare the real
shift of ee_T_cam with the linearised prediction and with the total sigma (per ee axis). Also
prints what refining the intrinsics in the graph would do (data_step_px, data_sigma_px on the
unmoved solve): the bias and the confidence of option (c).

    .venv/bin/python bench/camera_model.py --sim-seeds 0,1,2 [--sigma 2,2,5,5] [--params cx,cy]
    .venv/bin/python bench/camera_model.py --datasets A B [--predictions NAME] [--sigma 2,2,3,3]
        # B: A with a moved K, re-predicted (the frontend's depths then depend on K too): A's
        # prediction vs B - A; --sigma replaces dataset.yaml's params_sigma (as solve --intrinsics-sigma-px)

Writes bench/results/camera_model.json.
"""

import argparse
import json
import sys
import tempfile
from pathlib import Path

import gtsam
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from calib3r_graph.io.dataset import load_dataset  # noqa: E402
from calib3r_graph.io.predictions import choose_predictions, load_predictions  # noqa: E402
from calib3r_graph.io.results import tangent_in_ee_frame, uncertainty_report  # noqa: E402
from calib3r_graph.simulate import SimOptions, simulate  # noqa: E402
from calib3r_graph.solver.camera_model import PARAMS, with_moved_intrinsics, with_params_sigma  # noqa: E402
from calib3r_graph.solver.solve import SolveOptions, solve  # noqa: E402

AXES = ("x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg")


def load(root, name=None):
    ds = load_dataset(root)
    name = choose_predictions(ds, name)
    return ds, load_predictions(ds.root, name, ds.cameras, set(ds.frames), skip_missing=True)


def compare(label, sol, moved, param, camera="cam0") -> dict:
    X = sol.ee_T_cam[camera]
    R = X.rotation().matrix()
    cm = sol.camera_model[camera]
    real = tangent_in_ee_frame(R, gtsam.Pose3.Logmap(X.between(moved.ee_T_cam[camera])))
    pred = tangent_in_ee_frame(R, cm.shift_per_sigma[param]) if param in cm.shift_per_sigma else None
    total = uncertainty_report(X, sol.covariance[camera])["sigma_ee_frame"]
    rest = uncertainty_report(X, np.asarray(sol.covariance[camera]) - cm.covariance)["sigma_ee_frame"]
    row = {"case": label, "param": param, "real": real, "predicted": pred, "total_sigma": total,
           "sigma_without_camera_model": rest, "ratio": {a: real[a] / total[a] for a in AXES},
           "ratio_without": {a: real[a] / rest[a] for a in AXES},
           "data_sigma_px": dict(zip(PARAMS, cm.data_sigma_px or [])),
           "data_step_px": dict(zip(PARAMS, cm.data_step_px or []))}
    f = lambda d: " ".join(f"{d[a]:7.3f}" for a in AXES)
    print(f"{label} {param}: shift     {f(real)}  (x y z mm, rx ry rz deg)")
    if pred:
        print(f"{'':{len(label)}}      predicted {f(pred)}")
    worst = max(map(abs, row["ratio"].values()))
    print(f"{'':{len(label)}}      total     {f(total)}   |shift|/total max {worst:.2f}, "
          f"without the camera model {max(map(abs, row['ratio_without'].values())):.1f}")
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sim-seeds", default="")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--sigma", help="fx, fy, cx, cy 1-sigma (px); simulator default 2,2,5,5")
    ap.add_argument("--params", default="cx,cy")
    ap.add_argument("--datasets", nargs=2, metavar=("A", "B"))
    ap.add_argument("--predictions")
    args = ap.parse_args()
    opt = SolveOptions(progress=False, jackknife="never")
    stated = tuple(float(x) for x in args.sigma.split(",")) if args.sigma else None
    sigma = stated or (2.0, 2.0, 5.0, 5.0)
    rows = []
    for seed in [int(s) for s in args.sim_seeds.split(",") if s]:
        with tempfile.TemporaryDirectory() as tmp:
            root = simulate(Path(tmp) / "d", SimOptions(seed=seed, frames=args.frames, images=False), progress=False)
            ds, preds = load(root, "sim")
            ds = with_params_sigma(ds, sigma, "--sigma")
            sol = solve(ds, preds, opt)
            cm = sol.camera_model["cam0"]
            print(f"sim seed {seed}: camera model {sol.stats['timings_s']['camera_model']:.2f} s of "
                  f"{sum(sol.stats['timings_s'].values()):.1f} s; refining in the graph would move "
                  + ", ".join(f"{p} {s:+.2f} px (data sigma {d:.2f})" for p, s, d in
                              zip(PARAMS, cm.data_step_px, cm.data_sigma_px))
                  + " (truth: 0)")
            for p in args.params.split(","):
                moved = solve(*with_moved_intrinsics(ds, preds, "cam0", p, sigma[PARAMS.index(p)]), opt)
                rows.append(compare(f"sim seed {seed}", sol, moved, p))
    if args.datasets:
        (ds, preds), (ds2, preds2) = load(args.datasets[0], args.predictions), load(args.datasets[1], args.predictions)
        ds, ds2 = with_params_sigma(ds, stated, "--sigma"), with_params_sigma(ds2, stated, "--sigma")
        moved_by = {p: b - a for p, a, b in zip(PARAMS, ds.cameras["cam0"].params, ds2.cameras["cam0"].params)
                    if b != a}
        sol, moved = solve(ds, preds, opt), solve(ds2, preds2, opt)
        for p, d in moved_by.items():
            print(f"{args.datasets[1]}: {p} moved by {d:+.2f} px (its sigma {ds.cameras['cam0'].params_sigma})")
            rows.append(compare(str(args.datasets[0]), sol, moved, p))
    out = Path(__file__).resolve().parent / "results" / "camera_model.json"
    out.write_text(json.dumps(rows, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
