"""The guard every ``compare`` method runs under: what marks a method "failed: <reason>", never "ok".

A library exception (OpenCV, GTSAM, numpy), a failure OpenCV only prints (captured at the
file-descriptor level), a non-finite result or covariance, a reflection, a flange motion that
cannot fix the hand-eye, pattern-ba's corner noise far above the per-image PnP fit's, and a result
whose own AX = XB residual on the board is absurd against what the board allows (board_check).
"""

import contextlib
import os
import re
import sys
import tempfile

import gtsam
import numpy as np

from calib3r_graph.errors import Calib3rError, SolveError, library_error

# The methods that use the board (board_check judges the others by it only where one of these fits it).
PATTERN_METHODS = ["tsai", "park", "horaud", "andreff", "daniilidis", "pattern-ba"]


class MethodFailed(SolveError):
    """A method ran, and what it returned cannot be right (compare reports "failed: <reason>")."""


# A result is absurd when it fits its own data this many times worse than the data allow: the
# per-image fit (PnP) for pattern-ba's corner noise, the noise of PnP and of the robot and the best
# method for the AX = XB residual. Valid methods fit the same equations, so they differ by a small
# factor: on rwhe_kuka_1 and tabb_ds1, whole and halved, every pattern method's rotation residual is
# 1.2-2.1x the predicted noise and its translation residual within 2.4x of the best method's
# (docs/compare.md). A wrong answer (a flipped board, a solver that gave up) is 1000x off.
ABSURD_FACTOR = 10.0
# The translation residual gets a wider factor: it grows with a motion that leaves one axis weak and
# with the arm's absolute position error, the rotation residual does not. On rwhe_kuka_2's orbit,
# whole and halved, andreff and both two-stage pipelines leave 6.6-11 mm (11-19x the best method's
# 0.56-0.67 mm) at the best method's rotation residual (0.04-0.07 deg): weak, not garbage. Garbage
# shows in rotation (68-150 deg) or at 1000x (the importer's refusal uses the same split).
ABSURD_FACTOR_TRANSLATION = 30.0
# OpenCV reports some failures only by printing them (calibrateHandEye's Tsai returns R = I, t = 0
# after "Hand-eye calibration failed! Not enough informative motions--include larger rotations.").
PRINTED_FAILURE = re.compile(r"[\w-]*\s*calibration failed[^\n]*", re.IGNORECASE)
# What a method can raise when it breaks on the data (OpenCV, GTSAM's RuntimeError, numpy);
# anything else is a bug and is not hidden.
METHOD_EXCEPTIONS = (np.linalg.LinAlgError, RuntimeError, ValueError, ArithmeticError)


@contextlib.contextmanager
def printed_output():
    """Capture what libraries print on stdout and stderr inside the block, at the file-descriptor
    level (C++ code writes there, past Python's sys.stdout); yields a list that holds the text
    afterwards. The text is passed on to stderr, so nothing the user would have seen is lost."""
    sys.stdout.flush()
    sys.stderr.flush()
    out = []
    try:
        saved = [os.dup(1), os.dup(2)]
    except OSError:  # no standard descriptors to capture (a closed stdout): nothing printed can be read
        yield [""]
        return
    with tempfile.TemporaryFile() as tmp:
        try:
            os.dup2(tmp.fileno(), 1)
            os.dup2(tmp.fileno(), 2)
            yield out
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            tmp.seek(0)
            out.append(tmp.read().decode(errors="replace"))
            if out[0]:
                sys.stderr.write(out[0])
                sys.stderr.flush()


def _exception_reason(e) -> str:
    described = library_error(e)
    if described is not None:
        return described[0]
    first = next((line.strip() for line in str(e).splitlines() if line.strip()), "")
    return f"{type(e).__name__}: {first}" if first else type(e).__name__


def check_result(X: dict, cov: dict):
    """MethodFailed unless every camera's ee_T_cam is finite and a rotation (det R = +1, R^T R = I,
    within 1e-6) and every covariance is finite."""
    for c, T in X.items():
        M = np.asarray(T.matrix())
        if not np.all(np.isfinite(M)):
            raise MethodFailed(f"{c}: the result is not finite (NaN or inf in ee_T_cam)")
        R = M[:3, :3]
        det = float(np.linalg.det(R))
        if abs(det - 1) > 1e-6 or np.abs(R.T @ R - np.eye(3)).max() > 1e-6:
            raise MethodFailed(f"{c}: the result is " + (f"a reflection (det R = {det:.3f})" if det < 0 else
                                                         f"not a rotation (det R = {det:.6f})"))
    for c, C in cov.items():
        if not np.all(np.isfinite(np.asarray(C))):
            raise MethodFailed(f"{c}: its covariance is not finite (±inf or NaN sigmas)")


def check_flange_motion(base_T_ee: dict, frames):
    if not rotates_about_two_axes(base_T_ee, frames):
        raise MethodFailed(f"the flange rotates about fewer than two axes among the {len(set(frames))} poses it "
                           "used: AX = XB leaves the hand-eye undetermined")


def guarded(run, base_T_ee: dict, capture_printed: bool):
    """({camera: ee_T_cam}, {camera: 6x6 covariance}) of ``run() -> (X, cov, used)`` under the guard
    (compare.run_method): a SolveError passes through; an OpenCV, GTSAM or numpy exception and a
    failure OpenCV only prints (``capture_printed``) become MethodFailed, and so does a result that
    cannot be right (check_result, a flange motion about fewer than two axes among the frames
    ``used`` lists per camera)."""
    try:
        with printed_output() if capture_printed else contextlib.nullcontext([""]) as printed:
            X, cov, used = run()
    except Calib3rError:
        raise
    except METHOD_EXCEPTIONS + _library_exceptions() as e:
        raise MethodFailed(_exception_reason(e)) from e
    said = PRINTED_FAILURE.search(printed[0] if printed else "")
    if said:
        raise MethodFailed(f"OpenCV printed '{said.group(0).strip()}'")
    for poses in used:  # the frames each camera's result rests on (the board's, for the pattern methods)
        check_flange_motion(base_T_ee, poses)
    check_result(X, cov)
    return X, cov


def _library_exceptions() -> tuple:
    import cv2

    return (cv2.error,)


def check_pattern_ba(res, dets: dict):
    """pattern-ba's calibrated corner noise against the per-image PnP fit's (which fits each image
    alone, so it is the least the corners allow): a joint fit ABSURD_FACTOR x worse, or not finite,
    has not found a mount that explains the images."""
    uv_rms = np.sqrt(np.mean([d.reprojection_px ** 2 for ds_ in dets.values() for d in ds_]))
    figures = [res.corner_sigma_px, res.robot_noise_factor, res.board_scale]
    if not np.all(np.isfinite(figures)):
        raise MethodFailed(f"non-finite fit (corner noise {res.corner_sigma_px:.3g} px, robot poses "
                           f"{res.robot_noise_factor:.3g}x their sigma, board scale {res.board_scale:.3g})")
    if res.corner_sigma_px > ABSURD_FACTOR * uv_rms:
        raise MethodFailed(f"corner noise {res.corner_sigma_px:.3g} px is {res.corner_sigma_px / uv_rms:.0f}x the "
                           f"per-image PnP fit's {uv_rms:.3g} px: no mount explains the images and the poses")


def board_residuals(base_T_ee: dict, dets: list, X) -> tuple[float, float]:
    """A result's own AX = XB residual on the board: the RMS rotation (rad) and translation (m) of
    ``base_T_board_i = base_T_ee_i ee_T_cam cam_T_board_i`` (each image's PnP) about their mean. The
    board does not move, so the right ee_T_cam makes them one pose up to the noise of PnP and robot."""
    from calib3r_graph.geometry import mean_pose

    P = [base_T_ee[d.frame].compose(X).compose(d.cam_T_board) for d in dets]
    M = mean_pose(P)
    dev = [M.between(p) for p in P]
    rot = np.sqrt(np.mean([np.sum(gtsam.Rot3.Logmap(d.rotation()) ** 2) for d in dev]))
    return float(rot), float(np.sqrt(np.mean([np.sum(d.translation() ** 2) for d in dev])))


def board_noise(ds, camera: str, dets: list, noise) -> tuple[float, float]:
    """What the board allows that residual to be with the right ee_T_cam: the RMS rotation (rad) and
    translation (m) spread of base_T_board from each image's PnP covariance (its Jacobian, scaled by
    the image's own reprojection error) and the robot's nominal noise (``noise``; the flange's rotation
    error moves the board by its distance)."""
    import cv2

    from calib3r_graph.evaluation.pattern import board_points

    cam, obj_all = ds.cameras[camera], board_points(ds.pattern)
    var_r, var_t = [], []
    for d in dets:
        obj = obj_all if d.ids is None else obj_all[np.asarray(d.ids)]
        rvec, _ = cv2.Rodrigues(d.cam_T_board.rotation().matrix())
        _, J = cv2.projectPoints(obj, rvec, d.cam_T_board.translation(), cam.K, cam.dist)
        J = J[:, :6]
        n = len(obj)
        sigma2 = d.reprojection_px ** 2 * n / max(2 * n - 6, 1)  # per image coordinate, less PnP's 6 dof
        C = sigma2 * np.linalg.pinv(J.T @ J)
        lever = np.linalg.norm(d.cam_T_board.translation())
        var_r.append(np.trace(C[:3, :3]) + 3 * np.radians(noise.robot_sigma_deg) ** 2)
        var_t.append(np.trace(C[3:, 3:]) + 3 * (noise.robot_sigma_mm * 1e-3) ** 2
                     + 2 * (lever * np.radians(noise.robot_sigma_deg)) ** 2)
    return float(np.sqrt(np.mean(var_r))), float(np.sqrt(np.mean(var_t)))


def own_uncertainty_residual(base_T_ee: dict, dets: list, X, cov, k=3.0) -> tuple[float, float]:
    """What a result's own reported uncertainty lets its board residual grow by: the largest rise of
    board_residuals (rotation rad, translation m; as a root-sum-square increase) when ee_T_cam moves
    by ``k`` sigma along each principal axis of its 6x6 tangent covariance ``cov``. A result that is
    off along an axis the motion cannot observe, and says so with a large sigma there, leaves a
    residual that large (rwhe_kuka_2's orbit: ours 14 mm off along the optical axis with a 7 mm
    sigma, 5.7 mm of residual); that is not a garbage result."""
    r0, t0 = board_residuals(base_T_ee, dets, X)
    lam, vec = np.linalg.eigh(0.5 * (np.asarray(cov) + np.asarray(cov).T))
    extra_r = extra_t = 0.0
    for l, v in zip(np.maximum(lam, 0), vec.T):
        for sign in (1, -1):
            r, t = board_residuals(base_T_ee, dets, X.compose(gtsam.Pose3.Expmap(sign * k * np.sqrt(l) * v)))
            extra_r, extra_t = max(extra_r, np.sqrt(max(r * r - r0 * r0, 0))), max(extra_t, np.sqrt(max(t * t - t0 * t0, 0)))
    return float(extra_r), float(extra_t)


def board_check(ds, detections: dict, solved: dict, noise, covariances: dict | None = None) -> dict:
    """The guard's last part, on the board's motion (needs every method's result): per camera, each
    result's AX = XB residual (board_residuals) against what the board allows, which is the larger of
    the PnP and robot noise (board_noise) and the best method's residual. A result ABSURD_FACTOR x
    beyond it in rotation, or ABSURD_FACTOR_TRANSLATION x in translation, has failed; so has one whose rotation residual is ABSURD_FACTOR x the noise alone (the
    rotation part needs no scale, unit or robot translation accuracy), even when every method is
    that far off (a flipped board, mispaired images). Methods that do not use the board are judged
    by it only where some pattern method fits it. ``covariances``: {method: {camera: 6x6}} of the
    methods that report one; each such result is allowed what its own 3 sigma adds to its residual
    (own_uncertainty_residual) on top, so a wide but honest sigma is not taken for garbage.

    Returns ``{"failed": {method: reason}, "residuals": {method: {camera: {"rotation_deg",
    "translation_mm"}}}, "allows": {camera: {"rotation_deg", "translation_mm", "noise_rotation_deg",
    "noise_translation_mm", "best"}}}``."""
    failed, residuals, allows = {}, {}, {}
    for c, dets in detections.items():
        if len(dets) < 3:
            continue
        res = {m: board_residuals(ds.base_T_ee, dets, X[c]) for m, X in solved.items() if c in X}
        if not res:
            continue
        n_rot, n_t = board_noise(ds, c, dets, noise)
        own = {m: own_uncertainty_residual(ds.base_T_ee, dets, solved[m][c], covariances[m][c])
               for m in res if c in (covariances or {}).get(m, {})}
        own_r, own_t = (lambda m: own.get(m, (0.0, 0.0))[0]), (lambda m: own.get(m, (0.0, 0.0))[1])
        fits = {m for m, (r, _) in res.items() if r <= ABSURD_FACTOR * n_rot + own_r(m)}
        board_fits = bool(fits & set(PATTERN_METHODS))  # some method that uses the board fits it
        judged = {m for m in res if m in PATTERN_METHODS or board_fits}
        best = min(fits, key=lambda m: res[m][0] / n_rot + res[m][1] / n_t) if fits else None
        a_rot, a_t = (max(n_rot, res[best][0]), max(n_t, res[best][1])) if best else (n_rot, n_t)
        allows[c] = {"rotation_deg": float(np.degrees(a_rot)), "translation_mm": a_t * 1e3,
                     "noise_rotation_deg": float(np.degrees(n_rot)), "noise_translation_mm": n_t * 1e3,
                     "best": best}
        for m, (r, t) in res.items():
            residuals.setdefault(m, {})[c] = {"rotation_deg": float(np.degrees(r)), "translation_mm": t * 1e3}
            if m not in judged or m in failed:
                continue
            what = f"{c}: its own AX = XB residual on the board is {np.degrees(r):.3g} deg / {t * 1e3:.3g} mm RMS"
            if m not in fits:
                failed[m] = (f"{what}, {r / n_rot:.0f}x the {np.degrees(n_rot):.2g} deg that the PnP and robot "
                             "noise allow (a flipped board, mispaired images and poses, or a solver that gave up)")
            elif r > ABSURD_FACTOR * a_rot + own_r(m) or t > ABSURD_FACTOR_TRANSLATION * a_t + own_t(m):
                failed[m] = (f"{what}, {max(r / a_rot, t / a_t):.0f}x what the board allows ({np.degrees(a_rot):.2g} "
                             f"deg / {a_t * 1e3:.2g} mm: the best method, {best}, or the PnP and robot noise)"
                             + (f", beyond the {np.degrees(own_r(m)):.2g} deg / {own_t(m) * 1e3:.2g} mm its own 3 sigma "
                                "explain" if m in own else ""))
    return {"failed": failed, "residuals": residuals, "allows": allows}


def rotates_about_two_axes(base_T_ee: dict, frames, min_angle_deg=5.0, min_axis_deg=20.0) -> bool:
    """Whether the flange's relative motions among ``frames`` include two rotations of at least
    ``min_angle_deg`` about axes at least ``min_axis_deg`` apart (in the flange frame): what
    AX = XB needs to fix the hand-eye rotation and translation."""
    from calib3r_graph.solver.uncertainty import relative_rotations

    w = relative_rotations(base_T_ee, list(frames))
    norm = np.linalg.norm(w, axis=1)
    axes = w[norm >= np.radians(min_angle_deg)] / norm[norm >= np.radians(min_angle_deg), None]
    if len(axes) < 2:
        return False
    return bool(np.abs(axes @ axes.T).min() <= np.cos(np.radians(min_axis_deg)))
