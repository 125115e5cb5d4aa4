"""Is a difference explained by the stated uncertainties? Per ee axis, in sigmas.

Two results ``ee_T_cam`` A and B, each with per-axis sigmas in the ee frame (``sigma_ee_frame``:
rx, ry, rz in degrees, x, y, z in mm), differ per ee axis by

    d_t = t_A - t_B (mm, ee frame),      d_r = Log(R_A R_B^T) (deg, ee frame),

and each component is judged against ``sqrt(sigma_A^2 + sigma_B^2)`` (the two results treated as
independent). ``|d| / sigma <= 3`` on every axis is the acceptance used for real recordings.

A reference judges a tolerance only if it repeats between the two halves of the recording at
least 3x better than that tolerance (``reference_validation``).
"""

import gtsam
import numpy as np

AXES = ["rx_deg", "ry_deg", "rz_deg", "x_mm", "y_mm", "z_mm"]


def axis_differences(A: gtsam.Pose3, B: gtsam.Pose3) -> np.ndarray:
    """[rx, ry, rz] in degrees and [x, y, z] in mm, in the ee frame: A minus B."""
    d_r = np.degrees(gtsam.Rot3.Logmap(A.rotation().compose(B.rotation().inverse())))
    return np.concatenate([d_r, (A.translation() - B.translation()) * 1e3])


def sigma_vector(sigma_ee_frame: dict | None) -> np.ndarray:
    if not sigma_ee_frame:
        return np.zeros(6)
    return np.array([sigma_ee_frame[a] for a in AXES], float)


def in_sigmas(A, sigma_A: dict | None, B, sigma_B: dict | None) -> dict:
    """Per-axis difference, combined sigma and their ratio; ``max_ratio`` over the axes that have a sigma."""
    d = axis_differences(A, B)
    s = np.hypot(sigma_vector(sigma_A), sigma_vector(sigma_B))
    ratio = np.where(s > 0, np.abs(d) / np.where(s > 0, s, 1.0), np.nan)
    return {"difference": dict(zip(AXES, d.tolist())), "sigma": dict(zip(AXES, s.tolist())),
            "ratio": dict(zip(AXES, ratio.tolist())),
            "max_ratio": float(np.nanmax(ratio)) if np.isfinite(ratio).any() else None}


def consistency(result: dict, reference_method: str) -> dict:
    """{method: {camera: in_sigmas(...)}} of every method that reports a sigma against the reference
    method of the same comparison (a compare() result)."""
    from calib3r_graph.io.dataset import ee_T_cam_by_camera

    ref = result["methods"].get(reference_method)
    if not ref or ref["status"] != "ok":
        return {}
    ref_X = ee_T_cam_by_camera(ref["cameras"])
    out = {}
    for m, r in result["methods"].items():
        if m == reference_method or r["status"] != "ok":
            continue
        X = ee_T_cam_by_camera(r["cameras"])
        cams = {c: in_sigmas(X[c], r["cameras"][c].get("sigma_ee_frame"), ref_X[c],
                             ref["cameras"][c].get("sigma_ee_frame"))
                for c in X if c in ref_X and r["cameras"][c].get("sigma_ee_frame")}
        if cams:
            out[m] = cams
    return out


def halves_consistency(first: dict, second: dict) -> dict:
    """{method: {camera: in_sigmas(first half, second half)}}: the halves' difference in sigmas of a difference."""
    from calib3r_graph.io.dataset import ee_T_cam_by_camera

    out = {}
    for m, a in first["methods"].items():
        b = second["methods"].get(m)
        if not b or a["status"] != "ok" or b["status"] != "ok":
            continue
        Xa, Xb = ee_T_cam_by_camera(a["cameras"]), ee_T_cam_by_camera(b["cameras"])
        cams = {c: in_sigmas(Xa[c], a["cameras"][c].get("sigma_ee_frame"), Xb[c], b["cameras"][c].get("sigma_ee_frame"))
                for c in Xa if c in Xb and a["cameras"][c].get("sigma_ee_frame")}
        if cams:
            out[m] = cams
    return out


def reference_validation(halves_result: dict, reference_method: str, tolerance_mm: float, tolerance_deg: float) -> dict:
    """Does the reference repeat between the halves at least 3x better than the tolerance it judges?"""
    r = halves_result["methods"].get(reference_method)
    if not r or r["status"] != "ok" or not r["cameras"]:
        return {"reference": reference_method, "validated": False,
                "reason": f"{reference_method} could not be solved on both halves"}
    et = max(e["e_t_m"] for e in r["cameras"].values()) * 1e3
    er = np.degrees(max(e["e_theta_rad"] for e in r["cameras"].values()))
    ok = 3 * et <= tolerance_mm and 3 * er <= tolerance_deg
    return {"reference": reference_method, "halves_mm": et, "halves_deg": float(er),
            "tolerance_mm": tolerance_mm, "tolerance_deg": tolerance_deg, "validated": bool(ok),
            "smallest_tolerance_judged_mm": 3 * et, "smallest_tolerance_judged_deg": float(3 * er),
            "reason": (f"{reference_method} repeats between the halves to {et:.2f} mm / {er:.3f} deg: "
                       + ("validated" if ok else "NOT validated") +
                       f" for {tolerance_mm:g} mm / {tolerance_deg:g} deg (it judges tolerances from "
                       f"{3 * et:.1f} mm / {3 * er:.2f} deg up)")}


def sigma_table(cons: dict, title: str) -> str:
    """A markdown table of per-axis differences in sigmas."""
    lines = [title, "", "| method | camera | " + " | ".join(AXES) + " | max |", "|---|---|" + "---|" * 7]
    for m, cams in cons.items():
        for c, e in cams.items():
            cells = [f"{e['difference'][a]:+.2f} / {e['sigma'][a]:.2f} = {e['ratio'][a]:.1f}σ" for a in AXES]
            lines.append(f"| {m} | {c} | " + " | ".join(cells) + f" | {e['max_ratio']:.1f}σ |")
    return "\n".join(lines) + "\n"
