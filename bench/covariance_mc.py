"""Monte Carlo study of covariance consistency: over seeds, the normalised estimation error
squared (NEES) of ee_T_cam under the reported covariance, and of the metric scale.

A consistent 6-dof covariance gives mean NEES = 6 and 99 % of runs inside chi2_6(0.99). The
reported covariance is the total (noise model + systematic part, covering the leave-one-pose-out
jackknife below 15 poses); the modelled one before the jackknife and the noise model's alone are
given beside it (the simulator's robot noise is white, so those two should nearly agree).
Writes bench/results/covariance_mc.json and a PNG of predicted vs. actual errors.

    .venv/bin/python bench/covariance_mc.py [--runs 30 --frames 12 --cameras 1]
"""

import argparse
import json
import sys
import tempfile
from pathlib import Path

import gtsam
import numpy as np
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from calib3r_graph.io.dataset import load_dataset, load_ground_truth  # noqa: E402
from calib3r_graph.io.predictions import load_predictions  # noqa: E402
from calib3r_graph.simulate import SimOptions, simulate  # noqa: E402
from calib3r_graph.solver.solve import SolveOptions, solve  # noqa: E402


def one_run(seed, frames, cameras):
    with tempfile.TemporaryDirectory() as tmp:
        root = simulate(Path(tmp) / "d", SimOptions(seed=seed, frames=frames, cameras=cameras, images=False),
                        progress=False)
        ds = load_dataset(root)
        preds = load_predictions(root, "sim", ds.cameras, set(ds.frames))
        sol = solve(ds, preds, SolveOptions(progress=False))
        gt = load_ground_truth(root)
    out = []
    for cam, X in sol.ee_T_cam.items():
        xi = gtsam.Pose3.Logmap(X.between(gt["hand_eye"][cam]))  # X_true = X_hat Exp(xi)
        cov = sol.covariance[cam]
        lam, lam_sigma = sol.metric_scale[cam]
        lam_true = np.exp(np.mean([np.log(v["metres_per_depth_unit"]) for k, v in gt["views"].items()
                                   if k.startswith(cam + "/")]))
        jk = sol.stats.get("jackknife", {}).get(cam)
        modelled = np.array(jk["covariance_before"]) if jk else cov  # noise model + field, before the jackknife
        out.append({"seed": seed, "camera": cam, "nees": float(xi @ np.linalg.solve(cov, xi)),
                    "nees_modelled": float(xi @ np.linalg.solve(modelled, xi)), "jackknife": jk is not None,
                    "nees_model": float(xi @ np.linalg.solve(sol.covariance_model[cam], xi)),
                    "field_mm_per_m": sol.systematic[cam].gradient_mm_per_m,
                    "err": xi.tolist(), "sigma": np.sqrt(np.diag(cov)).tolist(),
                    "nees_scale": float(((lam - lam_true) / lam_sigma) ** 2),
                    **sol.stats["noise_calibration"]})
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--runs", type=int, default=30)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--cameras", type=int, default=1)
    ap.add_argument("--plot", default=str(Path(__file__).parent / "results" / "covariance_mc.png"))
    args = ap.parse_args()
    rows = []
    for seed in range(args.runs):
        rows += one_run(1000 + seed, args.frames, args.cameras)
        print(f"run {seed + 1}/{args.runs}: NEES {rows[-1]['nees']:.2f}", file=sys.stderr)
    nees = np.array([r["nees"] for r in rows])
    nees_s = np.array([r["nees_scale"] for r in rows])
    inside = float(np.mean(nees < stats.chi2.ppf(0.99, 6)))
    summary = {"runs": args.runs, "frames": args.frames, "cameras": args.cameras,
               "nees_mean": float(nees.mean()), "nees_median": float(np.median(nees)),
               "inside_chi2_6_99": inside, "nees_scale_mean": float(nees_s.mean()),
               "nees_model_mean": float(np.mean([r["nees_model"] for r in rows])),
               "nees_modelled_mean": float(np.mean([r["nees_modelled"] for r in rows])),
               "jackknife_runs": int(sum(r["jackknife"] for r in rows)),
               "field_mm_per_m_median": float(np.median([r["field_mm_per_m"] for r in rows]))}
    print(json.dumps(summary, indent=2))
    out = Path(args.plot).parent
    out.mkdir(parents=True, exist_ok=True)
    (out / "covariance_mc.json").write_text(json.dumps({"summary": summary, "runs": rows}, indent=2))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    err = np.abs(np.array([r["err"] for r in rows]))
    sig = np.array([r["sigma"] for r in rows])
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].loglog(np.degrees(sig[:, :3]).ravel(), np.degrees(err[:, :3]).ravel(), ".", label="rotation (deg)")
    ax[0].loglog(sig[:, 3:].ravel() * 1e3, err[:, 3:].ravel() * 1e3, ".", label="translation (mm)")
    lim = [min(ax[0].get_xlim()[0], ax[0].get_ylim()[0]), max(ax[0].get_xlim()[1], ax[0].get_ylim()[1])]
    ax[0].plot(lim, lim, "k--", lw=0.8, label="|error| = sigma")
    ax[0].plot(lim, [3 * l for l in lim], "k:", lw=0.8, label="3 sigma")
    ax[0].set_xlabel("predicted sigma per axis")
    ax[0].set_ylabel("actual |error| per axis")
    ax[0].legend()
    ax[1].hist(nees, bins=20, density=True, alpha=0.7, label="NEES of ee_T_cam")
    x = np.linspace(0, max(30, nees.max()), 200)
    ax[1].plot(x, stats.chi2.pdf(x, 6), "k", label="chi2(6)")
    ax[1].set_xlabel("NEES")
    ax[1].legend()
    fig.suptitle(f"{args.runs} runs, {args.frames} poses, {args.cameras} camera(s): mean NEES {nees.mean():.1f}, "
                 f"{100 * inside:.0f} % inside chi2_6(0.99)")
    fig.tight_layout()
    fig.savefig(args.plot, dpi=110)


if __name__ == "__main__":
    main()
