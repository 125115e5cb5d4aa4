"""Live calibration on the real recordings and the simulator: recorded, guided and random orders.

For each recording (``../shared/real``: imported with ``calib3r-graph import``, the pairwise
frontend run frame by frame with its features and pair geometries cached under ``--cache``) and a
simulated dataset (its own predictions), the recording is replayed through ``LiveSession``:

* per step: the error of ee_T_cam to the full recording's batch ``solve`` (mm, deg), the largest
  total sigma (mm, deg), and whether the error is within 3 sigma on every ee axis (coverage);
* the frames each order needs to come within 3 mm / 0.2 deg of the full result and stay there
  (median and range over the random order's ``--seeds``, and the ratio to the recorded order);
* the same at 2, 4 and 5 mm, and within the full result's own largest total sigma (mm and deg):
  each recording's own accuracy as the tolerance;
* ``--orders ...,oracle``: a greedy order that knows the full result (:func:`oracle_order`, on the
  full result's linearised graph), replayed through the real engine as a fixed order, with the
  linearised model's own frames-to-3 mm for it and for the recorded order; ``sigma_oracle``: the
  guide's own criterion with each frame's true factors (:func:`sigma_oracle_order`), the order a guide
  that predicted every match exactly would take; ``--order-file`` replays
  any fixed order;
* the latency of each update (the solver's part; the frontend's feature extraction, pair geometry
  and aggregation and the guidance's scoring reported apart) and all updates against one batch solve;
* the final live result against batch solve, in sigma per ee axis (the equivalence goal);
* ``--empty-pair-cache``: each replay computes its pairs' two-view geometry as a live capture does,
  instead of reading them from ``--cache`` (the features are still read; the new image's feature
  extraction is timed apart on five images of each recording).

The linearised and re-solving jackknives are compared by ``bench/jackknife.py``.

    .venv/bin/python bench/live_real.py [--recordings rwhe_kuka_1,rwhe_kuka_2,tabb_ds1,sim] [--seeds 20]
        [--seed-start 0] [--work DIR] [--cache DIR] [--out bench/results]
    .venv/bin/python bench/live_real.py --merge A/live_real.json B/live_real.json [--out bench/results]

Writes ``OUT/live_real.json``, ``OUT/live_real.md`` and ``OUT/live_real_<recording>.png``.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # see bench/views_real.py: set before numpy loads

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import gtsam  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from _workdirs import add_work_args, work_dirs  # noqa: E402  (bench/, the script's own folder)
from calib3r_graph.geometry import pose_error  # noqa: E402
from calib3r_graph.io.dataset import load_dataset  # noqa: E402
from calib3r_graph.io.predictions import load_predictions  # noqa: E402
from calib3r_graph.io.results import covariance_in_ee_frame, largest_sigma, uncertainty_report  # noqa: E402
from calib3r_graph.live.run import replay  # noqa: E402
from calib3r_graph.live.session import LiveSession  # noqa: E402
from calib3r_graph.solver import jackknife as jk  # noqa: E402
from calib3r_graph.solver.graph import NoiseOptions  # noqa: E402
from calib3r_graph.solver.solve import SolveOptions, solve  # noqa: E402

log = logging.getLogger("live_real")
SHARED = ROOT.parent / "shared" / "real"
BOARDS = {"rwhe_kuka_1": (28, 17), "rwhe_kuka_2": (24, 17)}
NEAR_MM, NEAR_DEG = 3.0, 0.2
SWEEP_MM = (2.0, 3.0, 4.0, 5.0)
SIGMA_FACTORS = (1.25, 1.5, 2.0)  # multiples of the full result's total sigma (frames_to_stay_below_sigma)


def prepare(name, work: Path, cache: Path):
    """(dataset dir, predictions name or None, batch predictions, reference Solution, (batch solve wall s,
    its CPU s))."""
    from calib3r_graph.frontends.pairwise import pairwise_predictions

    ds_dir = work / name
    if name == "sim":
        if not (ds_dir / "dataset.yaml").exists():
            from calib3r_graph.simulate import SimOptions, simulate

            simulate(ds_dir, SimOptions(seed=11, frames=30, cameras=1, images=False, matches_per_pair=500), progress=False)
        ds = load_dataset(ds_dir)
        preds, pname = load_predictions(ds_dir, "sim", ds.cameras, set(ds.frames)), "sim"
    else:
        if not (ds_dir / "dataset.yaml").exists():
            from calib3r_graph.importers import import_recording

            src = SHARED / name
            import_recording("tabb" if (src / "robot_cali.txt").exists() else "rwhe", src, ds_dir, BOARDS.get(name),
                             progress=False)
        ds = load_dataset(ds_dir)
        preds, pname = pairwise_predictions(ds, None, cache_dir=cache / name, progress=False), None
    opt = SolveOptions(noise=NoiseOptions(pixel_sigma_px=float(preds.info.get("match_noise_px", 1.0))), progress=False)
    t, c = time.perf_counter(), time.process_time()
    ref = solve(ds, preds, opt)
    return ds_dir, pname, preds, ref, (time.perf_counter() - t, time.process_time() - c)


def feature_extraction_s(ds_dir, n=5) -> float | None:
    """The median wall time of the pairwise frontend's feature extraction on the first ``n`` images of
    the first camera (what a live update's new image costs before its pairs; None without images)."""
    from calib3r_graph.frontends.pairwise import PairwiseOptions, extract_features

    ds = load_dataset(ds_dir)
    cam = next(iter(ds.cameras.values()))
    if ds.image_path(cam.name, ds.frames[0]) is None:
        return None
    times = []
    for frame in ds.frames[:n]:
        t = time.perf_counter()
        extract_features(ds, cam, frame, PairwiseOptions())
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def ee_z(X, ref, C) -> np.ndarray:
    """(rx, ry, rz, x, y, z) of X against ref in the ee frame, in sigmas of C (ref's covariance)."""
    d = gtsam.Pose3.Logmap(ref.between(X))
    R = ref.rotation().matrix()
    return np.r_[R @ d[:3], R @ d[3:]] / np.sqrt(np.diag(covariance_in_ee_frame(ref, np.asarray(C))))


def run_order(ds_dir, pname, cache, ref, order, seed, fixed=None):
    """One replay; ``fixed``: the frame order of a fixed order ("oracle", "file")."""
    session = LiveSession(ds_dir, predictions=pname, cache_dir=cache, guide=False, seed=seed)
    steps = []

    def record(up):
        row = {"frames": len(up.frames), "latency_s": up.latency_s, "cpu_s": up.cpu_s, "frontend_s": up.frontend_s,
               "frontend_cpu_s": up.frontend_cpu_s, "guidance_s": up.guidance_s, "message": up.message}
        if up.ee_T_cam:
            cams = {}
            for c, T in up.ee_T_cam.items():
                X = gtsam.Pose3(np.array(T))
                t_err, r_err = pose_error(X, ref.ee_T_cam[c])
                d = gtsam.Pose3.Logmap(ref.ee_T_cam[c].between(X))
                R = X.rotation().matrix()
                e = np.abs(np.r_[np.degrees(R @ d[:3]), 1e3 * (R @ d[3:])])
                s = up.sigma_ee_frame[c]
                sig = np.array([s["rx_deg"], s["ry_deg"], s["rz_deg"], s["x_mm"], s["y_mm"], s["z_mm"]])
                cams[c] = {"error_mm": 1e3 * t_err, "error_deg": r_err, "sigma_mm": float(sig[3:].max()),
                           "sigma_deg": float(sig[:3].max()), "covered": bool(np.all(e <= 3 * sig))}
            row["cameras"] = cams
        steps.append(row)

    t = time.perf_counter()
    replay(session, fixed if fixed is not None else order, seed, on_update=record)
    wall = time.perf_counter() - t
    final = {}
    if session.sol is not None:
        for c, X in session.sol.ee_T_cam.items():
            final[c] = ee_z(X, ref.ee_T_cam[c], ref.covariance[c]).tolist()
    return {"order": order, "seed": seed, "steps": steps, "wall_s": wall, "final_z": final,
            "frames_order": list(session.base_T_ee),  # arrival order
            "cold_restarts": session.engine.cold_restarts}  # warm updates solved again from scratch (engine)


class LinearModel:
    """The full result's linearised graph (solver/jackknife.factor_system about the full solution):
    the estimate from a subset of frames is ``full + dx``, ``dx = H_S^-1 sum_S A^T b`` over the
    factors whose views all belong to the subset (the scale gauge kept on the views left), a view
    or variable that no kept factor touches left out. Cheap enough for a greedy oracle that tries
    every unused frame at every step (the sums grow by the new frame's factors only)."""

    def __init__(self, ref):
        from calib3r_graph.io.predictions import split_view_id

        self.H, self.offsets, factors = jk.factor_system(ref.graph, ref.values)
        keys = ref.keys
        self.he = {c: self.offsets[keys.hand_eye(c)][0] for c in ref.ee_T_cam}
        frame_of = {}
        for v in ref.base_T_cam:
            for k in (keys.pose(v), keys.scale(v), keys.correction(v)):
                frame_of[k] = split_view_id(v)[1]
        gauge_keys = {keys.metric(c) for c in ref.ee_T_cam}
        self.gauge_cols = [self.offsets[k][0] for k in gauge_keys]
        self.factors, self.gauge = [], []  # (frames it needs, columns, A^T A, A^T b); gauge: + each column's frame
        for ks, idx, AtA, Atb, _ in factors:
            if set(ks) & gauge_keys:
                self.gauge.append((idx, AtA, Atb, [frame_of.get(k) for k in ks for _ in range(self.offsets[k][1])]))
            else:
                self.factors.append((frozenset(frame_of[k] for k in ks if k in frame_of), idx, AtA, Atb))

    def state(self, frames: set, base=None, new=None):
        """(H, b, touched) summed over the non-gauge factors of ``frames``; with ``base`` (the state of
        ``frames - {new}``) only the factors that need ``new`` are added to it."""
        n = len(self.H)
        H, b, touched = (np.zeros((n, n)), np.zeros(n), np.zeros(n, bool)) if base is None else \
            (base[0].copy(), base[1].copy(), base[2].copy())
        for need, idx, AtA, Atb in self.factors:
            if need <= frames and (new is None or new in need):
                H[np.ix_(idx, idx)] += AtA
                b[idx] += Atb
                touched[idx] = True
        return H, b, touched

    def covariance(self, frames: set, state):
        """{camera: the noise model's covariance of ee_T_cam} from the subset's information (the inverse
        of its reduced H), or None where the subset does not determine it. ``state``: of ``frames``."""
        H, _, touched = self._with_gauge(frames, state)
        keep = np.flatnonzero(touched)
        try:
            Hinv = np.linalg.inv(np.linalg.cholesky(H[np.ix_(keep, keep)]))
        except np.linalg.LinAlgError:
            return None
        pos = {k: i for i, k in enumerate(keep)}
        out = {}
        for c, a in self.he.items():
            if not touched[a]:
                return None
            cols = [pos[a + i] for i in range(6)]
            L = Hinv[:, cols]
            out[c] = L.T @ L
        return out

    def _with_gauge(self, frames: set, state):
        H, b, touched = state[0].copy(), state[1].copy(), state[2].copy()
        for idx, AtA, Atb, col_frames in self.gauge:
            keep = np.array([f is None or f in frames for f in col_frames])
            H[np.ix_(idx[keep], idx[keep])] += AtA[np.ix_(keep, keep)]
            b[idx[keep]] += Atb[keep]
        touched[self.gauge_cols] = True
        return H, b, touched

    def error(self, frames: set, state):
        """{camera: (mm, deg)} of the subset's estimate to the full result, or None where the subset
        does not determine it (singular, or a step past the linear range). ``state``: of ``frames``."""
        H, b, touched = self._with_gauge(frames, state)
        keep = np.flatnonzero(touched)
        try:
            L = np.linalg.cholesky(H[np.ix_(keep, keep)])
        except np.linalg.LinAlgError:
            return None
        dx = np.zeros(len(H))
        dx[keep] = np.linalg.solve(L.T, np.linalg.solve(L, b[keep]))
        out = {}
        for c, a in self.he.items():
            w, v = dx[a:a + 3], dx[a + 3:a + 6]
            if not touched[a] or np.linalg.norm(w) > jk.MAX_STEP[0] or np.linalg.norm(v) > jk.MAX_STEP[1]:
                return None
            out[c] = (1e3 * float(np.linalg.norm(v)), float(np.degrees(np.linalg.norm(w))))
        return out


def near_score(err) -> float:
    """max over cameras of max(mm / 3, deg / 0.2): 1 or less is within 3 mm / 0.2 deg."""
    return float("inf") if err is None else max(max(mm / NEAR_MM, deg / NEAR_DEG) for mm, deg in err.values())


def oracle_order(ref, base_T_ee: dict, progress=True) -> tuple[list, list]:
    """(order, [near_score after each frame]): greedy, knowing the full result: at each step the
    unused frame whose addition brings the linearised estimate (:class:`LinearModel`) closest to the
    full result, in :func:`near_score`. Until the first subset that determines the hand-eye, the
    frame whose flange rotation differs most from those used (as the guided replay starts). Only
    frames the full result used are ordered (the others, e.g. left out as not co-visible, follow)."""
    return _greedy(ref, base_T_ee, lambda model, order, S, state: near_score(model.error(S, state)), "oracle",
                   progress)


def sigma_score(ref, base_T_ee: dict, frames: list, covs) -> float:
    """The guide's own criterion (solver/guidance.py's ``objective``, the scale's term left out) with the
    subset's true information: the root sum of squares of sigma / (3 mm, 0.2 deg) over the six ee axes,
    summed over the cameras, the sigma being the subset's noise-model covariance
    (:meth:`LinearModel.covariance`) plus the full result's systematic part scaled by the squared
    systematic-error gain of the subset's motion against the full one's (guidance.score_candidates' first
    pass)."""
    from calib3r_graph.solver.guidance import objective
    from calib3r_graph.solver.uncertainty import systematic_error_gain

    if covs is None:
        return float("inf")
    g_full = systematic_error_gain(base_T_ee, sorted(f for f in base_T_ee))[0]
    g = systematic_error_gain(base_T_ee, frames)[0]
    f = (g / g_full) ** 2 if np.isfinite(g) and g_full > 0 else float("inf")
    if not np.isfinite(f):
        return float("inf")
    total = {c: C + f * np.asarray(ref.systematic[c].covariance) for c, C in covs.items()}
    return objective(total, ref.ee_T_cam, {c: 0.0 for c in total}, 1.0, NEAR_MM, NEAR_DEG)


def sigma_oracle_order(ref, base_T_ee: dict, progress=True) -> tuple[list, list]:
    """Greedy on the guide's criterion with what the guide can only predict known: at each step the unused
    frame whose addition gives the smallest :func:`sigma_score` on the full result's linearised graph
    (:class:`LinearModel`: the frame's true factors to the frames used). It does not know the full
    result, so unlike :func:`oracle_order` it cannot pick frames whose errors happen to cancel: it is
    what a guide that predicted every match exactly would do. The start as :func:`oracle_order`'s."""
    return _greedy(ref, base_T_ee, lambda model, order, S, state: sigma_score(ref, base_T_ee, order,
                                                                              model.covariance(S, state)),
                   "sigma oracle", progress)


def _greedy(ref, base_T_ee: dict, score, desc: str, progress: bool) -> tuple[list, list]:
    """(order, [score after each frame]): at each step the unused frame with the lowest
    ``score(model, order with it, its set, the model's state of that set)``; where none is finite,
    the frame whose flange rotation differs most from those used."""
    from tqdm import tqdm

    model = LinearModel(ref)
    solved = set(ref.frames)
    frames = [f for f in base_T_ee if f in solved]
    order, scores = [frames[0]], [float("inf")]
    cur = model.state(set(order))
    rest = frames[1:]
    bar = tqdm(total=len(rest), desc=desc, disable=not progress, leave=False)
    while rest:
        tries = {}
        for g in rest:
            S = set(order) | {g}
            tries[g] = score(model, order + [g], S, model.state(S, cur, g))
        best = min(rest, key=lambda g: tries[g])
        if not np.isfinite(tries[best]):
            R = [base_T_ee[f].rotation() for f in order]
            best = max(rest, key=lambda g: min(np.linalg.norm(gtsam.Rot3.Logmap(r.between(base_T_ee[g].rotation())))
                                               for r in R))
        order.append(best)
        scores.append(tries[best])
        cur = model.state(set(order), cur, best)
        rest.remove(best)
        bar.update()
    bar.close()
    return order + [f for f in base_T_ee if f not in solved], scores


def linear_scores(ref, order: list) -> list:
    """:func:`near_score` of the linearised estimate after each frame of ``order``."""
    model = LinearModel(ref)
    cur, used, out = None, set(), []
    for f in order:
        used.add(f)
        cur = model.state(used, cur, f if cur is not None else None)
        out.append(near_score(model.error(used, cur)))
    return out


def linear_frames_to_near(scores, counts) -> int | None:
    """Fewest frames after which every later linearised score is within 3 mm / 0.2 deg."""
    for i in range(len(scores)):
        if all(s <= 1 for s in scores[i:]):
            return counts[i]
    return None


def frames_to_stay_near(steps, mm=NEAR_MM, deg=NEAR_DEG) -> int | None:
    """Fewest frames after which every later update is within ``mm`` / ``deg`` of the full result."""
    return _frames_to_stay(steps, "error", mm, deg)


def frames_to_stay_below_sigma(steps, mm, deg) -> int | None:
    """Fewest frames after which every later update's largest total sigma is within ``mm`` / ``deg``:
    when the stop rule at that target says done (its sigma is honest where the 3 sigma coverage holds)."""
    return _frames_to_stay(steps, "sigma", mm, deg)


def _frames_to_stay(steps, what, mm, deg) -> int | None:
    """Fewest frames after which every later update's ``what`` ("error" or "sigma") is within ``mm`` /
    ``deg`` on every camera (the last step, finish(), left out)."""
    ok = [("cameras" in s and all(c[f"{what}_mm"] <= mm and c[f"{what}_deg"] <= deg for c in s["cameras"].values()))
          for s in steps[:-1]]
    for i in range(len(ok)):
        if all(ok[i:]):
            return steps[i]["frames"]
    return None


def summarise(runs, batch_s, batch_cpu_s=None, full_sigma=None):
    """Per order; ``full_sigma``: the full result's largest total sigma (mm, deg), the tolerance of
    ``frames_to_own_sigma`` (its own accuracy, where 3 mm / 0.2 deg is finer or coarser than that)."""
    out = {}
    for order in ("recorded", "guided", "random", "oracle", "sigma_oracle", "file"):
        rs = [r for r in runs if r["order"] == order]
        if not rs:
            continue
        need = [frames_to_stay_near(r["steps"]) for r in rs]
        cov = [c["covered"] for r in rs for s in r["steps"][:-1] for c in s.get("cameras", {}).values()]
        lat = [s["latency_s"] for r in rs for s in r["steps"][:-1] if "cameras" in s]
        total = [sum(s["latency_s"] for s in r["steps"]) for r in rs]
        front = [sum(sum(s["frontend_s"].values()) for s in r["steps"]) for r in rs]
        z = [max(abs(v) for c in r["final_z"].values() for v in c) for r in rs if r["final_z"]]
        got = [n for n in need if n is not None]
        # the same count at other tolerances: where the full result's own sigma is near 3 mm, the
        # count is decided by a step that lands just outside (docs/live-notes.md, "How far can an order go?")
        sweep = {}
        for mm in SWEEP_MM:
            n = [frames_to_stay_near(r["steps"], mm) for r in rs]
            sweep[str(mm)] = {"median": float(np.median([x for x in n if x is not None])) if any(
                x is not None for x in n) else None, "never": sum(x is None for x in n), "all": n}
        own = [frames_to_stay_near(r["steps"], *full_sigma) for r in rs] if full_sigma else []
        # the frames until the total sigma is within SIGMA_FACTORS x the full result's (the stop rule's view)
        sig = {}
        for k in (SIGMA_FACTORS if full_sigma else ()):
            n = [frames_to_stay_below_sigma(r["steps"], k * full_sigma[0], k * full_sigma[1]) for r in rs]
            sig[str(k)] = {"median": float(np.median([x for x in n if x is not None])) if any(
                x is not None for x in n) else None, "never": sum(x is None for x in n), "all": n}
        out[order] = {"sweep_mm_at_0.2deg": sweep, "sigma_within_full_x": sig, "runs": len(rs),
                      "frames_to_3mm_0.2deg": need,
                      "frames_to_own_sigma": own,
                      "own_sigma_median": float(np.median([x for x in own if x is not None])) if any(
                          x is not None for x in own) else None,
                      "frames_median": float(np.median(got)) if got else None,
                      "frames_range": [min(got), max(got)] if got else None, "never_near": len(need) - len(got),
                      "coverage_3sigma": float(np.mean(cov)) if cov else None,
                      "latency_median_s": float(np.median(lat)) if lat else None,
                      "latency_at_max_frames_s": float(np.median([r["steps"][-2]["latency_s"] for r in rs])),
                      "updates_total_s": float(np.median(total)), "frontend_total_s": float(np.median(front)),
                      "updates_over_batch": float(np.median(total) / batch_s), "final_max_abs_z": max(z) if z else None,
                      **_speed(rs, batch_cpu_s)}
    return out


def _speed(rs, batch_cpu_s) -> dict:
    """CPU times (time.process_time, the same process: other work on the machine does not stretch them)
    and the update a user waits for: the solver's part plus the frontend's pair geometry, rescue and
    aggregation (the new image's feature extraction apart) and, in the guided order, the guidance's
    scoring, at 20 frames and more (wall; the CPU figure leaves the guidance out)."""
    steps = [s for r in rs for s in r["steps"][:-1] if "cameras" in s]
    late = [s for s in steps if s["frames"] >= 20]
    front = lambda s: sum(v for k, v in s["frontend_s"].items() if k != "features")  # noqa: E731
    cpu_total = [sum(s.get("cpu_s", 0.0) for s in r["steps"]) for r in rs]
    med = lambda x: float(np.median(x)) if x else None  # noqa: E731
    return {"cpu_median_s": med([s["cpu_s"] for s in steps if "cpu_s" in s]),
            "updates_cpu_total_s": med(cpu_total),
            "updates_cpu_over_batch_cpu": med(cpu_total) / batch_cpu_s if batch_cpu_s and cpu_total else None,
            # the last step is solve itself, in the same process under the same load as the updates
            "updates_cpu_over_finish_cpu": med([sum(s.get("cpu_s", 0.0) for s in r["steps"]) / r["steps"][-1]["cpu_s"]
                                                for r in rs if r["steps"] and r["steps"][-1].get("cpu_s")]),
            "guidance_median_s": med([s["guidance_s"] for s in steps if s.get("guidance_s")]),
            "update_with_frontend_median_s_from_20": med([s["latency_s"] + front(s) + s.get("guidance_s", 0.0)
                                                          for s in late]),
            "update_with_frontend_cpu_median_s_from_20": med([s["cpu_s"] + s["frontend_cpu_s"] for s in late
                                                               if "frontend_cpu_s" in s])}


COLOURS = {"recorded": "C0", "guided": "C3", "random": "C7", "oracle": "C2", "sigma_oracle": "C4", "file": "C1"}


def _draw(axes, runs, legend=True):
    """Error to the full result and largest total sigma against frames, one line per run, on two axes."""
    for r in runs:
        xs = [s["frames"] for s in r["steps"][:-1] if "cameras" in s]
        if not xs:
            continue
        err = [max(c["error_mm"] for c in s["cameras"].values()) for s in r["steps"][:-1] if "cameras" in s]
        sig = [max(c["sigma_mm"] for c in s["cameras"].values()) for s in r["steps"][:-1] if "cameras" in s]
        kw = {"color": COLOURS[r["order"]], "alpha": 0.35 if r["order"] == "random" else 1.0, "lw": 1}
        label = r["order"] if r["seed"] == 0 else None  # one legend entry per order
        axes[0].semilogy(xs, err, label=label, **kw)
        axes[1].semilogy(xs, sig, label=label, **kw)
    for ax, what in zip(axes, ("error to the full batch result (mm)", "largest total sigma (mm)")):
        ax.set_xlabel("frames")
        ax.set_title(what)
        ax.axhline(NEAR_MM if "error" in what else 1.0, color="k", lw=0.5, ls="--")
        if legend:
            ax.legend()


def plot(name, runs, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    _draw(axes, runs)
    fig.suptitle(f"live replay: {name}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_all(result, path):
    """One row per recording (error and sigma against frames, the three orders): the README's figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recs = list(result["recordings"].items())
    fig, axes = plt.subplots(len(recs), 2, figsize=(10, 2.6 * len(recs)), squeeze=False)
    for i, (name, rec) in enumerate(recs):
        _draw(axes[i], rec["runs"], legend=i == 0)
        for ax in axes[i]:
            ax.set_title(f"{name}: {ax.get_title()}", fontsize=9)
            if i < len(recs) - 1:
                ax.set_xlabel("")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def readme_table(result) -> str:
    """One row per recording, the figures the README shows: frames to 3 mm / 0.2 deg (medians), the
    lowest 3-sigma coverage of the three orders, all updates over the replay's own solve (CPU) and
    the median update with the frontend from 20 frames (wall)."""
    def per(rec, key, f, suffix=""):
        return " / ".join(fmt(rec["summary"].get(o, {}).get(key), f) + suffix
                          for o in ("recorded", "guided", "random"))

    lines = ["| recording (frames) | frames to 3 mm / 0.2°, recorded / guided / random | lowest 3σ coverage | "
             "all updates / own `solve` (CPU) | median update with frontend (s) |",
             "|---|---|---|---|---|"]
    for name, rec in result["recordings"].items():
        cov = [s["coverage_3sigma"] for s in rec["summary"].values() if s.get("coverage_3sigma") is not None]
        lines.append(f"| {name} ({rec['frames']}) | {per(rec, 'frames_median', 'g')} | "
                     f"{fmt(min(cov) if cov else None, '.0%')} | {per(rec, 'updates_cpu_over_finish_cpu', '.2f', '×')} | "
                     f"{per(rec, 'update_with_frontend_median_s_from_20', '.2f')} |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", default="rwhe_kuka_1,rwhe_kuka_2,tabb_ds1,sim")
    ap.add_argument("--seeds", type=int, default=20, help="random orders per recording")
    ap.add_argument("--seed-start", type=int, default=0,
                    help="the first random order's seed (to split one recording's random orders over processes)")
    ap.add_argument("--guided-seeds", type=int, default=1,
                    help="guided orders per recording: seed 0 starts at the first recorded frame, the others at a "
                         "seeded random frame")
    ap.add_argument("--guided-seed-start", type=int, default=0, help="the first guided start's seed")
    ap.add_argument("--orders", default="recorded,guided,random",
                    help="any of recorded, guided, random, oracle (greedy on the linearised full result), "
                         "sigma_oracle (greedy on the guide's criterion with the true factors)")
    ap.add_argument("--order-file", help="also replay this fixed order: frame ids, whitespace separated")
    ap.add_argument("--empty-pair-cache", action="store_true",
                    help="each replay computes its pairs' two-view geometry as a live capture does (a fresh pair "
                         "cache; the features are still read from --cache, their extraction timed apart)")
    ap.add_argument("--merge", nargs="+", metavar="JSON[:REC,...]",
                    help="replay nothing: merge these live_real.json files (e.g. one recording's orders run in two "
                         "processes), each whole or only the recordings named after a colon, into OUT's "
                         "live_real.{json,md} and plots; a recording in several files gets all their runs, summarised "
                         "against the batch solve of the first")
    add_work_args(ap, "live_real")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s: %(message)s")
    work, cache, out = work_dirs(args)
    if args.merge:
        return merge(args.merge, out)
    result = {"command": " ".join(sys.argv), "recordings": {}, "empty_pair_cache": args.empty_pair_cache}
    for name in args.recordings.split(","):
        if name != "sim" and not (SHARED / name).is_dir():
            print(f"{name}: not in {SHARED}, skipped")
            continue
        t = time.perf_counter()
        ds_dir, pname, preds, ref, (batch_s, batch_cpu_s) = prepare(name, work, cache)
        print(f"{name}: batch solve {batch_s:.1f} s (prepared in {time.perf_counter() - t:.0f} s)", flush=True)
        runs, fixed, linear = [], {}, {}
        wanted = args.orders.split(",")
        base_T_ee = load_dataset(ds_dir).base_T_ee
        if "oracle" in wanted:
            t = time.perf_counter()
            fixed["oracle"], _ = oracle_order(ref, base_T_ee, progress=False)
            print(f"  oracle order ({time.perf_counter() - t:.0f} s): {' '.join(fixed['oracle'])}", flush=True)
        if "sigma_oracle" in wanted:
            t = time.perf_counter()
            fixed["sigma_oracle"], _ = sigma_oracle_order(ref, base_T_ee, progress=False)
            print(f"  sigma oracle order ({time.perf_counter() - t:.0f} s): {' '.join(fixed['sigma_oracle'])}",
                  flush=True)
        if args.order_file:
            fixed["file"] = [x.strip() for x in Path(args.order_file).read_text().split() if x.strip()]
            wanted.append("file")
        for o in ("recorded", *fixed):
            order = list(base_T_ee) if o == "recorded" else fixed[o]
            sc = linear_scores(ref, order)
            linear[o] = linear_frames_to_near(sc, list(range(1, len(order) + 1)))
            print(f"  {o}: the linearised model puts it within 3 mm / 0.2 deg after {linear[o]} frames", flush=True)
        guided = range(args.guided_seed_start, args.guided_seed_start + args.guided_seeds)
        orders = (("recorded", [0]), ("guided", guided),
                  ("random", range(args.seed_start, args.seed_start + args.seeds)), ("oracle", [0]), ("sigma_oracle", [0]),
                  ("file", [0]))
        for order, seeds in [(o, s) for o, s in orders if o in wanted]:
            for seed in seeds:
                if args.empty_pair_cache and name != "sim":
                    with tempfile.TemporaryDirectory(dir=work) as tmp:  # features only: every pair computed live
                        (Path(tmp) / "features").symlink_to((cache / name / "features").resolve())
                        r = run_order(ds_dir, pname, Path(tmp), ref, order, seed, fixed.get(order))
                else:
                    r = run_order(ds_dir, pname, cache / name, ref, order, seed, fixed.get(order))
                runs.append(r)
                print(f"  {order} {seed}: to 3 mm / 0.2 deg after {frames_to_stay_near(r['steps'])} frames, "
                      f"updates {sum(s['latency_s'] for s in r['steps']):.1f} s, final |z| "
                      f"{max((abs(v) for c in r['final_z'].values() for v in c), default=float('nan')):.3f}",
                      flush=True)
        full = {c: uncertainty_report(X, ref.covariance[c])["sigma_ee_frame"] for c, X in ref.ee_T_cam.items()}
        full_sigma = list(largest_sigma(full))
        rec = {"full_sigma_mm_deg": full_sigma, "feature_extraction_s": feature_extraction_s(ds_dir),
               "batch_solve_s": batch_s, "batch_solve_cpu_s": batch_cpu_s, "frames": len(load_dataset(ds_dir).frames),
               "summary": summarise(runs, batch_s, batch_cpu_s, full_sigma),
               "runs": runs, "fixed_orders": fixed, "linearised_frames_to_3mm_0.2deg": linear}
        result["recordings"][name] = rec
        plot(name, runs, out / f"live_real_{name}.png")
        (out / "live_real.json").write_text(json.dumps(result, indent=1, default=float))
    (out / "live_real.json").write_text(json.dumps(result, indent=1, default=float))
    (out / "live_real.md").write_text(table(result))
    plot_all(result, out / "live_real_all.png")
    print(table(result))


def merge(sources, out: Path):
    """``--merge``: the recordings of several live_real.json (``path`` or ``path:rec1,rec2``), runs of
    the same recording pooled (an order's seed once: the first file's run) and summarised again."""
    files = []
    for src in sources:
        path, _, names = src.partition(":")
        files.append((json.loads(Path(path).read_text()), set(names.split(",")) if names else None))
    result = {"command": "; ".join(d["command"] for d, _ in files) +
              f" (merged: bench/live_real.py --merge {' '.join(sources)})", "recordings": {},
              "empty_pair_cache": all(d.get("empty_pair_cache") for d, _ in files)}
    for data, only in files:
        for name, rec in data["recordings"].items():
            if only is not None and name not in only:
                continue
            have = result["recordings"].setdefault(name, {**rec, "runs": []})
            seen = {(r["order"], r["seed"]) for r in have["runs"]}
            have["runs"] += [r for r in rec["runs"] if (r["order"], r["seed"]) not in seen]
            have["fixed_orders"] = {**rec.get("fixed_orders", {}), **have.get("fixed_orders", {})}
            have["linearised_frames_to_3mm_0.2deg"] = {**rec.get("linearised_frames_to_3mm_0.2deg", {}),
                                                       **have.get("linearised_frames_to_3mm_0.2deg", {})}
    for name, rec in result["recordings"].items():
        rec["summary"] = summarise(rec["runs"], rec["batch_solve_s"], rec.get("batch_solve_cpu_s"),
                                   rec.get("full_sigma_mm_deg"))
        plot(name, rec["runs"], out / f"live_real_{name}.png")
    (out / "live_real.json").write_text(json.dumps(result, indent=1, default=float))
    (out / "live_real.md").write_text(table(result))
    plot_all(result, out / "live_real_all.png")
    print(table(result))


def fmt(v, f) -> str:
    return "–" if v is None else format(v, f)


def table(result) -> str:
    lines = [f"Command: `{result['command']}`", "",
             "| recording | order | runs | frames to 3 mm / 0.2° (median, range) | / recorded | 3σ coverage | "
             "median update (s) | update at all frames (s) | all updates / batch solve | frontend total (s) | "
             "final max \\|z\\| vs batch |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, rec in result["recordings"].items():
        for order, s in rec["summary"].items():
            rng = s.get("frames_range")
            need = fmt(s["frames_median"], ".0f") + (f" ({rng[0]}–{rng[1]})" if rng and s["runs"] > 1 else "") + (
                f", never: {s['never_near']}" if s.get("never_near") else "")
            rec_n = rec["summary"].get("recorded", {}).get("frames_median")
            ratio = fmt(s["frames_median"] / rec_n, ".2f") if rec_n and s["frames_median"] else "–"
            lines.append(f"| {name} ({rec['frames']} frames, batch {rec['batch_solve_s']:.1f} s) | {order} | {s['runs']} | "
                         f"{need} | {ratio} | {fmt(s['coverage_3sigma'], '.0%')} | "
                         f"{fmt(s['latency_median_s'], '.2f')} | {fmt(s['latency_at_max_frames_s'], '.2f')} | "
                         f"{fmt(s['updates_over_batch'], '.1f')}× | {fmt(s['frontend_total_s'], '.0f')} | "
                         f"{fmt(s['final_max_abs_z'], '.3f')} |")
    lines += ["", "Speed in CPU time (time.process_time of this process; the batch solve measured the same way, once "
              "before the replays, while the replay's own final step is solve itself under the load the updates ran "
              "under: the other core's load stretches CPU time too). \"With frontend\": the solver's part plus "
              "the pairwise frontend's pair geometry, rescue and aggregation (features from the cache, apart), the "
              "median over the updates at 20 frames and more" +
              ("; every replay computed its pairs' two-view geometry itself (an empty pair cache, as a live "
               "capture)" if result.get("empty_pair_cache") else "; the pairs' two-view geometry read from the "
               "cache") + ". The new image's feature extraction, apart (median of 5 images, wall): " +
              (", ".join(f"{n} {r['feature_extraction_s']:.2f} s" for n, r in result["recordings"].items()
                         if r.get("feature_extraction_s")) or "–") + ":", "",
              "| recording | order | batch solve CPU (s) | median update CPU (s) | all updates incl. final / batch (CPU) | "
              "all updates / the replay's own final solve (CPU) | median guidance (s, wall) | "
              "with frontend, wall (s) | with frontend, CPU (s) |",
              "|---|---|---|---|---|---|---|---|---|"]
    for name, rec in result["recordings"].items():
        for order, s in rec["summary"].items():
            lines.append(f"| {name} | {order} | {fmt(rec.get('batch_solve_cpu_s'), '.2f')} | "
                         f"{fmt(s.get('cpu_median_s'), '.2f')} | {fmt(s.get('updates_cpu_over_batch_cpu'), '.1f')}× | "
                         f"{fmt(s.get('updates_cpu_over_finish_cpu'), '.1f')}× | "
                         f"{fmt(s.get('guidance_median_s'), '.2f')} | "
                         f"{fmt(s.get('update_with_frontend_median_s_from_20'), '.2f')} | "
                         f"{fmt(s.get('update_with_frontend_cpu_median_s_from_20'), '.2f')} |")
    lines += ["", "Frames to stay within X mm / 0.2° of the full result (median over the runs; "
              "in brackets the ratio to the recorded order), against the full result's own largest total sigma:", "",
              "| recording | full result's sigma | order | runs | " + " | ".join(f"{mm:g} mm" for mm in SWEEP_MM) +
              " | within its own sigma (mm and deg) |",
              "|---|---|---|---|" + "---|" * (len(SWEEP_MM) + 1)]
    for name, rec in result["recordings"].items():
        sig = rec.get("full_sigma_mm_deg")
        for order, s in rec["summary"].items():
            cells = []
            for mm in SWEEP_MM:
                w = s.get("sweep_mm_at_0.2deg", {}).get(str(mm))
                r0 = rec["summary"].get("recorded", {}).get("sweep_mm_at_0.2deg", {}).get(str(mm), {}).get("median")
                if not w or w["median"] is None:
                    cells.append("never")
                    continue
                cell = f"{w['median']:.0f}" + (f" ({w['median'] / r0:.2f})" if r0 else "")
                cells.append(cell + (f", never {w['never']}" if w["never"] else ""))
            own, own_rec = s.get("frames_to_own_sigma"), rec["summary"].get("recorded", {}).get("own_sigma_median")
            if own:
                m = s.get("own_sigma_median")
                never = sum(x is None for x in own)
                cells.append(("never" if m is None else f"{m:.0f}" + (f" ({m / own_rec:.2f})" if own_rec else "")) +
                             (f", never {never}" if never and m is not None else ""))
            lines.append(f"| {name} | " + (f"{sig[0]:.1f} mm / {sig[1]:.3f}°" if sig else "–") +
                         f" | {order} | {s['runs']} | " + " | ".join(cells) + " |")
    lines += ["", "Frames until the largest total sigma is within k times the full result's and stays there (what "
              "the stop rule at that target sees; median over the runs, in brackets the ratio to the recorded "
              "order; the sigma is honest where the 3σ coverage above holds):", "",
              "| recording | full result's sigma | order | runs | " + " | ".join(f"{k:g}×" for k in SIGMA_FACTORS) + " |",
              "|---|---|---|---|" + "---|" * len(SIGMA_FACTORS)]
    for name, rec in result["recordings"].items():
        sig = rec.get("full_sigma_mm_deg")
        for order, s in rec["summary"].items():
            if not s.get("sigma_within_full_x"):
                continue
            cells = []
            for k in SIGMA_FACTORS:
                w = s["sigma_within_full_x"].get(str(k))
                r0 = rec["summary"].get("recorded", {}).get("sigma_within_full_x", {}).get(str(k), {}).get("median")
                if not w or w["median"] is None:
                    cells.append("never")
                    continue
                cells.append(f"{w['median']:.0f}" + (f" ({w['median'] / r0:.2f})" if r0 else "") +
                             (f", never {w['never']}" if w["never"] else ""))
            lines.append(f"| {name} | {sig[0]:.1f} mm / {sig[1]:.3f}° | {order} | {s['runs']} | " + " | ".join(cells) + " |")
    lines += ["", "The README's table (medians; recorded / guided / random):", "", readme_table(result).rstrip("\n")]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
