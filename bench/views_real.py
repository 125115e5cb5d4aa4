"""Few views on the real recordings: how often and how well the calibration solves from 6, 8
and 10 robot poses, against the same recording's full result.

For each recording and each number of views, ``--repeats`` seeded random subsets of the frames
whose flange motions rotate about at least two axes (``compare.random_subsets``) are solved
with the pairwise frontend (features and pair geometries computed once per recording and cached;
a subset only selects its pairs, aggregates and solves in-process, as ``solve --no-cloud``).
``jcr-predictions`` (the two-stage pipeline on the same predictions) runs on the same subsets.
With ``--colmap``, the colmap frontend (COLMAP's incremental mapper on the subset's images alone)
and ``jcr-colmap`` (the two-stage pipeline on that COLMAP trajectory) run on them as well.

The reference for every subset is the same recording's full result: all frames, the pairwise
frontend, solved the same way. The full colmap-frontend result and ``pattern-ba`` (the board
reference) are reported beside it. Every run is cached in ``CACHE/<recording>/views_real.jsonl``,
so a rerun only computes what is new.

    .venv/bin/python bench/views_real.py [--recordings rwhe_kuka_1,rwhe_kuka_2,tabb_ds1]
        [--views 6,8,10] [--repeats 20] [--colmap] [--work DIR] [--cache DIR] [--out bench/results]

``--work`` holds the datasets (``calib3r-graph import`` output; predictions/ may be written there).
Writes ``OUT/views_real.json``, ``OUT/views_real.md`` and ``OUT/views_real_<recording>.png``.
"""

import os

# One BLAS thread: the solver's many small products are up to 1000x slower when OpenBLAS's
# threads spin against other processes on a busy machine (measured: 254 ms instead of 0.26 ms
# for a 6000x24 J^T J at a load of 13 on 2 cores). Set before numpy loads.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import gtsam  # noqa: E402
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from calib3r_graph.errors import Calib3rError  # noqa: E402
from calib3r_graph.evaluation.compare import random_subsets, run_method, two_stage_hand_eye  # noqa: E402
from calib3r_graph.evaluation.consistency import in_sigmas  # noqa: E402
from calib3r_graph.frontends.pairwise import PairwiseOptions, pairwise_predictions  # noqa: E402
from calib3r_graph.geometry import pose_error  # noqa: E402
from calib3r_graph.io.dataset import load_dataset, subset_dataset  # noqa: E402
from calib3r_graph.io.predictions import load_predictions, read_poses_csv  # noqa: E402
from calib3r_graph.io.results import uncertainty_report  # noqa: E402
from calib3r_graph.solver.graph import NoiseOptions  # noqa: E402
from calib3r_graph.solver.solve import SolveOptions, solve  # noqa: E402

log = logging.getLogger("views_real")
METHODS = ["pairwise", "jcr-predictions", "colmap", "jcr-colmap", "park", "pattern-ba"]
PATTERN = ("park", "pattern-ba")  # measured against their own full-recording result
LABELS = {"pairwise": "calib3r-graph, pairwise frontend", "colmap": "calib3r-graph, colmap frontend",
          "jcr-predictions": "jcr-predictions (pairwise)", "jcr-colmap": "jcr-colmap",
          "park": "park (board; vs its own full result)", "pattern-ba": "pattern-ba (board; vs its own full result)"}
SOLVER_NOISE = {}  # --noise overrides of the solver's NoiseOptions (for experiments; default: none)
RUN_FIELDS = 3  # bump when run_pairwise records new fields, so cached runs are recomputed
FAILURES = (Calib3rError, RuntimeError, ValueError, np.linalg.LinAlgError)


class Store:
    """Runs cached as JSON lines: key -> result."""

    def __init__(self, path: Path):
        self.path = path
        self.data = {}
        if path.is_file():
            for line in path.read_text().splitlines():
                if line.strip():
                    rec = json.loads(line)
                    self.data[rec["key"]] = rec["value"]

    def get(self, key, compute):
        if key not in self.data:
            value = compute()
            self.data[key] = value
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "a") as f:
                f.write(json.dumps({"key": key, "value": value}) + "\n")
        return self.data[key]


def _cams(X: dict) -> dict:
    return {c: x.matrix().tolist() for c, x in X.items()}


def _attempt(fn):
    t = time.perf_counter()
    try:
        out = fn()
        out.setdefault("status", "ok")
    except FAILURES as e:
        out = {"status": f"error: {str(e).splitlines()[0] if str(e) else type(e).__name__}"}
    out["seconds"] = time.perf_counter() - t
    return out


def run_pairwise(ds, frames, opt, cache):
    """Ours with the pairwise frontend, and jcr-predictions on the same predictions."""
    sub = subset_dataset(ds, frames) if frames is not None else ds
    preds = pairwise_predictions(sub, None, opt, cache, progress=False)
    noise = NoiseOptions(pixel_sigma_px=preds.info["match_noise_px"], **SOLVER_NOISE)
    sol = solve(sub, preds, SolveOptions(noise=noise, progress=False))
    jk = sol.stats.get("jackknife", {})
    out = {"cameras": _cams(sol.ee_T_cam), "views_used": sol.stats["views_used"],
           "unusable_views": preds.info["unusable_views"],
           # per-axis sigmas (ee frame): the total, and the modelled one (noise model + robot field) that
           # the total covers together with the jackknife's spread below JACKKNIFE_BELOW poses
           "sigma": {c: uncertainty_report(X, sol.covariance[c])["sigma_ee_frame"] for c, X in sol.ee_T_cam.items()},
           "sigma_modelled": {c: uncertainty_report(X, np.array(jk[c]["covariance_before"]) if c in jk
                                                    else sol.covariance[c])["sigma_ee_frame"]
                              for c, X in sol.ee_T_cam.items()},
           # the pose the jackknife's data snooping names (solver/jackknife.influential_pose), if any
           "influential_pose": (sol.stats.get("influential_pose") or {}).get("frame"),
           # the noise model's alone: what the subset's own data can tell, with a perfect robot
           "sigma_noise_model": {c: uncertainty_report(X, sol.covariance_model[c])["sigma_ee_frame"]
                                 for c, X in sol.ee_T_cam.items()}}
    jcr = _attempt(lambda: {"cameras": _cams(run_method("jcr-predictions", sub, preds, noise)[0])})
    return out, jcr


def run_colmap(ds, frames):
    """Ours with the colmap frontend on the subset's images alone, and jcr-colmap on that trajectory."""
    from calib3r_graph.frontends.colmap import predict_colmap

    sub = subset_dataset(ds, frames) if frames is not None else ds
    if frames is None and (ds.root / "predictions" / "colmap" / "poses.csv").is_file():
        return _solve_colmap(sub, ds.root)  # the full recording's, made by `predict --frontend colmap`
    with tempfile.TemporaryDirectory(prefix="views-real-") as tmp:
        os.symlink(ds.root.resolve() / "images", Path(tmp) / "images")
        predict_colmap(dataclasses.replace(sub, root=Path(tmp)), "colmap", progress=False)
        return _solve_colmap(sub, Path(tmp))


def _solve_colmap(sub, root):
    """Ours on root/predictions/colmap, and jcr-colmap on its trajectory."""
    traj = read_poses_csv(Path(root) / "predictions" / "colmap" / "poses.csv")
    preds = load_predictions(root, "colmap", sub.cameras, set(sub.frames))
    jcr = _attempt(lambda: {"cameras": _cams(two_stage_hand_eye({v: gtsam.Pose3(T) for v, T in traj.items()},
                                                               sub.base_T_ee))})
    sol = _attempt(lambda: {"cameras": _cams(solve(sub, preds, SolveOptions(
        noise=NoiseOptions(pixel_sigma_px=float(preds.info.get("match_noise_px", 1.0)), **SOLVER_NOISE),
        progress=False)).ee_T_cam), "registered": preds.info.get("registered")})
    return sol, jcr


def pose_of(result, cam):
    return gtsam.Pose3(np.array(result["cameras"][cam])) if result.get("cameras", {}).get(cam) else None


def errors(result, ref, cam="cam0"):
    X, R = pose_of(result, cam), pose_of(ref, cam)
    if X is None or R is None:
        return None
    et, er = pose_error(X, R)
    return et * 1e3, er


def translation_difference(result, ref, cam="cam0"):
    """ee_T_cam's translation minus the reference's, in the ee frame (mm)."""
    return ((pose_of(result, cam).translation() - pose_of(ref, cam).translation()) * 1e3).tolist()


def shared_with_board(runs, n, other="park"):
    """Per ee axis, the correlation over the subsets of n views between ours' (pairwise) translation
    error and a board method's, each against its own full result: the part of the error that comes
    from the robot poses the subset happens to contain, which no frontend can remove."""
    by = {}
    for r in runs:
        if r["views"] == n and r.get("d_ee_mm") is not None:
            by.setdefault(r["repeat"], {})[r["method"]] = r["d_ee_mm"]
    pairs = [(v["pairwise"], v[other]) for v in by.values() if "pairwise" in v and other in v]
    if len(pairs) < 5:
        return None
    a, b = np.array(pairs).transpose(1, 0, 2)
    return {"subsets": len(pairs), "correlation": [float(np.corrcoef(a[:, i], b[:, i])[0, 1]) for i in range(3)],
            "rms_ours_mm": np.sqrt((a ** 2).mean(0)).tolist(), "rms_board_mm": np.sqrt((b ** 2).mean(0)).tolist()}


def bench_recording(name, args, opt):
    ds = load_dataset(Path(args.work) / name)
    cache = Path(args.cache) / name
    store = Store(cache / "views_real.jsonl")
    # the runs' key: the options and the frontend's and solver's code (an edit re-runs the subsets;
    # features and pair geometries have their own keys in the frontend's cache)
    frontend = sorted(str(f.relative_to(ROOT)) for f in (ROOT / "calib3r_graph/frontends/pairwise").glob("*.py"))
    code = b"".join((ROOT / f).read_bytes()
                     for f in (*frontend, "calib3r_graph/frontends/pose_check.py",
                               "calib3r_graph/frontends/pair_selection.py", "calib3r_graph/solver/solve.py",
                               "calib3r_graph/solver/views.py", "calib3r_graph/evaluation/guard.py",
                               "calib3r_graph/solver/jackknife.py", "calib3r_graph/solver/init.py"))
    digest = hashlib.sha1(json.dumps([dataclasses.asdict(opt), SOLVER_NOISE, RUN_FIELDS], sort_keys=True).encode()
                          + code).hexdigest()[:10]
    log.info("%s: %d frames", name, len(ds.frames))

    def pw(frames):
        key = f"pairwise {digest} {','.join(frames) if frames else 'all'}"
        return store.get(key, lambda: _pair_of(lambda: run_pairwise(ds, frames, opt, cache)))

    def cm(frames):
        key = f"colmap {','.join(frames) if frames else 'all'}"
        return store.get(key, lambda: _pair_of(lambda: run_colmap(ds, frames)))

    full_pw = pw(None)
    full = {"pairwise": full_pw[0], "jcr-predictions": full_pw[1]}
    if args.colmap:
        full_cm = cm(None)
        full.update({"colmap": full_cm[0], "jcr-colmap": full_cm[1]})
    full["pattern-ba"] = store.get("pattern-ba", lambda: _attempt(
        lambda: {"cameras": _cams(run_method("pattern-ba", ds, None, NoiseOptions())[0])}))
    board = {}

    def pattern(m, frames):
        """A board method on a subset, with the board detected once per recording."""
        if not board:
            from calib3r_graph.evaluation import pattern as pat

            board.update({c: pat.detect(ds, c) for c in ds.cameras})
        sub = subset_dataset(ds, frames) if frames else ds
        key = tuple(sub.base_T_ee)
        dets = {key: {c: [d for d in v if d.frame in sub.base_T_ee] for c, v in board.items()}, ("seconds",) + key: 0}
        return _attempt(lambda: {"cameras": _cams(run_method(m, ds, None, NoiseOptions(), frames, dets)[0])})

    if args.pattern:
        full["park"] = store.get("park", lambda: pattern("park", None))
    ref = full["pairwise"]
    if ref["status"] != "ok":
        raise SystemExit(f"{name}: the full recording does not solve with the pairwise frontend: {ref['status']}")
    runs = []
    for n in args.views:
        subsets = random_subsets(ds, n, args.repeats, args.seed)
        t0 = time.perf_counter()
        for r, frames in enumerate(subsets):
            got = dict(zip(("pairwise", "jcr-predictions"), pw(frames)))
            if args.colmap and r < (args.colmap_repeats or args.repeats):
                got.update(zip(("colmap", "jcr-colmap"), cm(frames)))
            if args.pattern:
                for m in PATTERN:
                    got[m] = store.get(f"{m} {','.join(frames)}", lambda: pattern(m, frames))
            for m, res in got.items():
                e = errors(res, full[m] if m in PATTERN else ref) if res["status"] == "ok" else None
                sig = _in_own_sigmas(res, ref) if m == "pairwise" and e else {}
                if m == "pairwise" and res["status"] == "ok":
                    sig["influential_pose"] = res.get("influential_pose")
                if m == "pairwise" and e and "sigma_noise_model" in res:
                    sig["sigma_noise_model_mm"] = [res["sigma_noise_model"]["cam0"][a] for a in ("x_mm", "y_mm", "z_mm")]
                runs.append({"views": n, "repeat": r, "frames": frames, "method": m, "status": res["status"], **sig,
                             "e_t_mm": e[0] if e else None, "e_theta_deg": e[1] if e else None,
                             "e_full_colmap": errors(res, full["colmap"]) if "colmap" in full and e else None,
                             "d_ee_mm": translation_difference(res, full[m] if m in PATTERN else ref) if e else None,
                             "seconds": res.get("seconds")})
        log.info("%s: %d views, %d subsets, %.0f s", name, n, len(subsets), time.perf_counter() - t0)
    return {"frames": len(ds.frames), "full": full, "runs": runs,
            "full_vs_reference": {m: errors(r, ref) for m, r in full.items() if r.get("status") == "ok"},
            "full_vs_pattern_ba": {m: errors(r, full["pattern-ba"]) for m, r in full.items()
                                   if r.get("status") == "ok" and full["pattern-ba"].get("status") == "ok"}}


def _in_own_sigmas(res, ref, cam="cam0") -> dict:
    """The largest per-axis |difference| to the full result in sigmas of the difference (the subset's
    sigma and the full result's combined), with the total sigma and with the modelled one."""
    if "sigma" not in res or "sigma" not in ref:
        return {}
    A, B = pose_of(res, cam), pose_of(ref, cam)
    return {f"max_sigma{k[5:]}": in_sigmas(A, res[k][cam], B, ref["sigma"][cam])["max_ratio"]
            for k in ("sigma", "sigma_modelled")}


def _pair_of(fn):
    """(ours, two-stage) results of one run, each with a status."""
    t = time.perf_counter()
    try:
        a, b = fn()
        a.setdefault("status", "ok")
    except FAILURES as e:
        msg = f"error: {str(e).splitlines()[0] if str(e) else type(e).__name__}"
        a, b = {"status": msg}, {"status": msg}
    a["seconds"] = time.perf_counter() - t
    return [a, b]


def summarise(runs, method, n):
    rs = [r for r in runs if r["method"] == method and r["views"] == n]
    if not rs:
        return None
    ok = [r for r in rs if r["status"] == "ok"]
    et = np.array([r["e_t_mm"] for r in ok])
    er = np.array([r["e_theta_deg"] for r in ok])
    return {"subsets": len(rs), "solved": len(ok),
            "median_mm": float(np.median(et)) if len(ok) else None,
            "median_deg": float(np.median(er)) if len(ok) else None,
            "p90_mm": float(np.percentile(et, 90)) if len(ok) else None,
            "p90_deg": float(np.percentile(er, 90)) if len(ok) else None,
            # of all subsets (a failure counts as outside)
            "within_5mm_03deg": float(np.sum((et <= 5) & (er <= 0.3)) / len(rs)),
            "within_3mm_02deg": float(np.sum((et <= 3) & (er <= 0.2)) / len(rs)),
            # of the solved subsets with sigmas: every axis within 3 sigma of the difference to the full result
            "within_3sigma": _share([r.get("max_sigma") for r in ok]),
            "within_3sigma_modelled": _share([r.get("max_sigma_modelled") for r in ok]),
            # the median over subsets of the noise model's sigma per ee axis (x, y, z): a lower bound
            # on the error along each axis that the subset's own data allow
            "poses_named": [(r["frames"], r["influential_pose"], r["e_t_mm"]) for r in ok if r.get("influential_pose")],
            "median_sigma_noise_model_mm": (np.median([r["sigma_noise_model_mm"] for r in ok], axis=0).tolist()
                                            if ok and all("sigma_noise_model_mm" in r for r in ok) else None)}


def _share(ratios):
    ratios = [x for x in ratios if x is not None]
    return float(np.mean(np.array(ratios) <= 3)) if ratios else None


def plot(name, res, views, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    methods = [m for m in METHODS if any(r["method"] == m for r in res["runs"])]
    colours = {"pairwise": "tab:red", "colmap": "tab:blue", "jcr-predictions": "tab:orange", "jcr-colmap": "tab:green",
               "park": "tab:grey", "pattern-ba": "black"}
    width = 0.8 / len(methods)
    for k, m in enumerate(methods):
        x = np.array(views) + (k - (len(methods) - 1) / 2) * width
        for a, key in ((ax[0], "e_t_mm"), (ax[1], "e_theta_deg")):
            vals = [[r[key] for r in res["runs"] if r["method"] == m and r["views"] == n and r[key] is not None]
                    for n in views]
            pos = [xi for xi, v in zip(x, vals) if v]
            bp = a.boxplot([v for v in vals if v], positions=pos, widths=width * 0.9, whis=(10, 90), sym="",
                           patch_artist=True, manage_ticks=False)
            for patch in bp["boxes"]:
                patch.set_facecolor(colours[m])
                patch.set_alpha(0.5)
        rates = [summarise(res["runs"], m, n)["solved"] / summarise(res["runs"], m, n)["subsets"] * 100 for n in views]
        ax[2].plot(x, rates, "os^vDx"[k] + "-", color=colours[m], label=LABELS[m], lw=2.5 if m == "pairwise" else 1)
    for a, lab, goal in ((ax[0], "e_t (mm) vs the full recording", (3, 5)),
                         (ax[1], "e_θ (deg) vs the full recording", (0.2, 0.3))):
        a.set_yscale("log")
        a.set_ylabel(lab)
        for g, ls in zip(goal, ("--", ":")):
            a.axhline(g, color="grey", ls=ls, lw=0.8)
        a.set_xticks(views)
        a.set_xlabel("robot poses (boxes: quartiles, whiskers 10-90 %)")
    ax[2].set_ylim(0, 105)
    ax[2].axhline(95, color="grey", ls="--", lw=0.8)
    ax[2].set_ylabel("subsets solved (%)")
    ax[2].set_xticks(views)
    ax[2].set_xlabel("robot poses")
    ax[2].legend(fontsize=8, loc="lower right")
    fig.suptitle(f"{name} ({res['frames']} frames): random subsets rotating about two axes, "
                 "errors against the full recording's result")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def markdown(results, views):
    lines = ["| recording | views | method | solved | median e_t (mm) | median e_θ (°) | 90 % e_t (mm) | "
             "90 % e_θ (°) | within 5 mm / 0.3° | within 3σ: modelled → total |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, res in results.items():
        for n in views:
            for m in METHODS:
                s = summarise(res["runs"], m, n)
                if s is None:
                    continue
                f = (lambda v, p: "–" if v is None else f"{v:.{p}f}")
                cover = "–" if s["within_3sigma"] is None else \
                    f"{100 * s['within_3sigma_modelled']:.0f} % → {100 * s['within_3sigma']:.0f} %"
                lines.append(f"| {name} | {n} | {m} | {s['solved']}/{s['subsets']} | {f(s['median_mm'], 2)} | "
                             f"{f(s['median_deg'], 3)} | {f(s['p90_mm'], 2)} | {f(s['p90_deg'], 3)} | "
                             f"{100 * s['within_5mm_03deg']:.0f} % | {cover} |")
    lines += ["", "Ours (pairwise) per ee axis x / y / z: the median over subsets of the noise model's own sigma (what "
              "the subset's data allow even with a perfect robot); the correlation of ours' and park's subset "
              "translation errors, each against its own full result (the share of the robot poses the subset "
              "happens to contain); and the rms of both.", "",
              "| recording | views | σ noise model (mm) | correlation with park | rms ours (mm) | rms park (mm) "
              "| poses named (e_t of the subset) |", "|---|---|---|---|---|---|---|"]
    j = (lambda v, p: "–" if v is None else " / ".join(f"{x:.{p}f}" for x in v))
    for name, res in results.items():
        for n in views:
            s, c = summarise(res["runs"], "pairwise", n), shared_with_board(res["runs"], n) or {}
            named = ", ".join(f"{f} ({e:.1f} mm)" for _, f, e in (s or {}).get("poses_named", [])) or "none"
            lines.append(f"| {name} | {n} | {j(s and s.get('median_sigma_noise_model_mm'), 1)} | "
                         f"{j(c.get('correlation'), 2)} | {j(c.get('rms_ours_mm'), 1)} | {j(c.get('rms_board_mm'), 1)} "
                         f"| {named} |")
    lines += ["", "| recording | full recording, method | vs full pairwise (mm, °) | vs pattern-ba (mm, °) |",
              "|---|---|---|---|"]
    for name, res in results.items():
        for m in ("pairwise", "colmap", "jcr-predictions", "jcr-colmap", "park"):
            a, b = res["full_vs_reference"].get(m), res["full_vs_pattern_ba"].get(m)
            if a is None and b is None:
                continue
            f = (lambda e: "–" if e is None else f"{e[0]:.2f}, {e[1]:.3f}")
            lines.append(f"| {name} | {m} | {f(a)} | {f(b)} |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recordings", default="rwhe_kuka_1,rwhe_kuka_2,tabb_ds1")
    ap.add_argument("--views", default="6,8,10")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--colmap", action="store_true", help="also the colmap frontend and jcr-colmap (slow)")
    ap.add_argument("--colmap-repeats", type=int, default=None,
                    help="run COLMAP on the first N subsets of each size only (30-60 s each on 2 cores)")
    ap.add_argument("--pattern", action="store_true",
                    help="also park and pattern-ba on the board, each against its own full-recording result: "
                         "how far a few poses move even a method with a known target")
    ap.add_argument("--work", default="/work/data/pairwise_work")
    ap.add_argument("--cache", default="/work/data/pairwise_cache")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    ap.add_argument("--noise", action="append", default=[], metavar="OPTION=VALUE",
                    help="override a solver NoiseOptions field for the prediction-based solves (experiments)")
    ap.add_argument("--set", action="append", default=[], metavar="OPTION=VALUE",
                    help="override a PairwiseOptions field (repeatable), e.g. --set rotation_tol_deg=0.5")
    args = ap.parse_args()
    args.views = [int(v) for v in args.views.split(",")]
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    for noisy in ("calib3r_graph",):
        logging.getLogger(noisy).setLevel(logging.ERROR)
    fields = {f.name: f.type for f in dataclasses.fields(PairwiseOptions)}
    overrides = {}
    for item in args.set:
        k, _, v = item.partition("=")
        if k not in fields:
            raise SystemExit(f"--set: unknown option '{k}' ({', '.join(fields)})")
        overrides[k] = {bool: lambda x: x.lower() in ("1", "true", "yes"), int: int}.get(fields[k], float)(v)
    opt = PairwiseOptions(**overrides)
    for item in args.noise:
        k, _, v = item.partition("=")
        SOLVER_NOISE[k] = float(v)
    results = {}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name in args.recordings.split(","):
        results[name] = bench_recording(name, args, opt)
        plot(name, results[name], args.views, out / f"views_real_{name}.png")
    table = markdown(results, args.views)
    summary = {name: {str(n): {m: summarise(res["runs"], m, n) for m in METHODS} for n in args.views}
               for name, res in results.items()}
    (out / "views_real.json").write_text(json.dumps({"options": dataclasses.asdict(opt), "args": vars(args),
                                                     "summary": summary, "results": results}, indent=1))
    (out / "views_real.md").write_text(table)
    print(table)


if __name__ == "__main__":
    main()
