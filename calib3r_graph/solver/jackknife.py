"""Leave-one-robot-pose-out cross-check of the reported covariance (``solve --jackknife``).

It re-runs the solver, so it sits above ``solve`` (and ``uncertainty``, which ``solve`` uses)."""

import numpy as np

from calib3r_graph.io.predictions import split_view_id


def jackknife(ds, preds, opt, sol, progress=True) -> dict:
    """Leave-one-robot-pose-out cross-check of the reported covariance (no ground truth needed).

    For each frame the problem is solved without it; the spread of ee_T_cam over the n
    solutions (in the tangent space at the full solution) gives the jackknife covariance
    ``(n - 1)/n * sum (xi_i - mean)(xi_i - mean)^T``. Returns, per camera, the jackknife
    sigmas and their ratio to the reported ones (about 1 when the covariance is right;
    large when it is over-confident, e.g. unmodelled correlated errors).
    """
    import dataclasses
    import logging

    frames = sorted({split_view_id(v)[1] for v in sol.base_T_cam})
    xis = {c: [] for c in sol.ee_T_cam}
    opt = dataclasses.replace(opt, progress=False)
    package_log = logging.getLogger("calib3r_graph")
    level = package_log.level
    package_log.setLevel(logging.ERROR)  # the sub-solves repeat the main solve's warnings
    try:
        _leave_one_out(ds, preds, opt, frames, xis, progress)
    finally:
        package_log.setLevel(level)
    return _jackknife_report(sol, xis)


def _leave_one_out(ds, preds, opt, frames, xis, progress):
    """Append each leave-one-frame-out solution's ee_T_cam to xis[camera]."""
    from tqdm import tqdm

    from calib3r_graph.errors import Calib3rError
    from calib3r_graph.io.dataset import subset_dataset
    from calib3r_graph.io.predictions import subset_predictions
    from calib3r_graph.solver.solve import solve

    for f in tqdm(frames, desc="jackknife", disable=None if progress else True, leave=False):
        keep = [g for g in frames if g != f]
        try:
            s = solve(subset_dataset(ds, keep), subset_predictions(preds, keep), opt)
        except Calib3rError:
            continue
        for c, X in s.ee_T_cam.items():
            if c in xis:
                xis[c].append(X)


def _jackknife_report(sol, xis) -> dict:
    import gtsam

    from calib3r_graph.io.results import covariance_in_ee_frame

    out = {}
    for c, xs in xis.items():
        if len(xs) < 3:
            continue
        xs = np.array([gtsam.Pose3.Logmap(sol.ee_T_cam[c].between(X)) for X in xs])
        n = len(xs)
        C = (n - 1) / n * (xs - xs.mean(0)).T @ (xs - xs.mean(0))
        jk = np.sqrt(np.diag(covariance_in_ee_frame(sol.ee_T_cam[c], C)))
        rep = np.sqrt(np.diag(covariance_in_ee_frame(sol.ee_T_cam[c], np.asarray(sol.covariance[c]))))
        out[c] = {"solves": n,
                  "sigma_jackknife": {"rx_deg": float(np.degrees(jk[0])), "ry_deg": float(np.degrees(jk[1])),
                                      "rz_deg": float(np.degrees(jk[2])), "x_mm": float(jk[3] * 1e3),
                                      "y_mm": float(jk[4] * 1e3), "z_mm": float(jk[5] * 1e3)},
                  "ratio_to_reported": [float(r) for r in jk / rep]}
    return out
