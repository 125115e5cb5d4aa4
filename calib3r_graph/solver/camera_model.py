"""The camera model's share of the total covariance: the intrinsics' own uncertainty, propagated.

The solver takes each camera's ``fx, fy, cx, cy`` as exact: every match is lifted to 3D with
them, ``P = d K^-1 [u, v, 1]`` (solver/observations.py), so a principal point off by a few
pixels shears every view's point cloud by ``d * dcx / fx`` and moves the hand-eye result by an
amount no noise-model marginal can show. Given the intrinsics' 1-sigma (``params_sigma`` in
dataset.yaml, written by ``import`` from the board calibration, or ``solve
--intrinsics-sigma-px F,C`` for factory values), this module adds ``Sigma_cam = J Sigma_theta
J^T`` to the total, with ``J = d(ee_T_cam, metric scale) / d(fx, fy, cx, cy)`` of the solved
graph.

**How J is found** (the implicit function theorem, as systematic.py does for the robot's
error field): at the solution the gradient of the graph's cost vanishes, ``g(x, theta) = 0``;
moving theta moves the solution by ``dx / dtheta = -H^-1 dg / dtheta``, with ``H`` the graph's
Gauss-Newton Hessian and ``dg / dtheta = sum_pairs J^T dE``: ``dE`` is the change of a pair's
whitened 3D match residual when its matches are re-lifted with K moved by ``+-sigma``
(central difference; the residual is linear in the lifted points) and ``J`` its whitened
Jacobian, both from factors.match3d's own functions. Only the 3D match factors see K (the
robot, rigidity and gauge factors do not; with ``--reprojection`` the reprojection factors'
dependence on K is left out). No re-solve: one pass over the pairs and one solve with H. On
the simulator it matches re-solving with each of fx, fy, cx, cy moved by 5 px within a few
percent (tests/test_camera_model.py; docs/camera-model-uncertainty.md).

The same differences give what the scene data alone say about theta: ``data_sigma_px``, from
the Schur complement of the scene information on theta (the rest of the graph free), and
``data_step_px``, the Gauss-Newton step that refining theta in the graph would take. These
are reported, not applied: whether refining the intrinsics in the graph would be right is
what they measure (docs/camera-model-uncertainty.md).

Not modelled: a frontend that triangulated its depths with K (pairwise, colmap) made depths
that depend on K too; the solver's per-view depth scale and smooth depth correction absorb the
part of that which is smooth. The measurements on rwhe_kuka_1 (re-predicting with the moved K)
are in docs/camera-model-uncertainty.md.
"""

import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np

from calib3r_graph.errors import InputError
from calib3r_graph.io.predictions import split_view_id
from calib3r_graph.solver.graph import depth_correction, scene_linearisation
from calib3r_graph.solver.systematic import linear_system

log = logging.getLogger(__name__)

PARAMS = ("fx", "fy", "cx", "cy")
NOT_PROPAGATED = ("camera model not in the sigma: the intrinsics carry no stated uncertainty (params_sigma in "
                  "dataset.yaml, or solve --intrinsics-sigma-px F,C)")


@dataclass
class CameraModelError:
    covariance: np.ndarray  # 6x6 on ee_T_cam's tangent [w, v] (rad, m), from every camera's intrinsics
    scale_sigma_rel: float  # relative sigma it adds to the metric scale
    params_sigma: tuple | None  # this camera's (fx, fy, cx, cy) 1-sigma (px), None: not given
    source: str  # where params_sigma came from
    shift_per_sigma: dict  # parameter -> (6,) tangent of ee_T_cam for +1 sigma of this camera's parameter
    data_sigma_px: list | None  # what the scene data alone tell about (fx, fy, cx, cy), px (inf: nothing)
    R_ee_cam: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(3))  # to report shifts in the ee frame
    data_step_px: list | None = None  # how far the scene data alone would move (fx, fy, cx, cy), px (one GN step)

    @property
    def propagated(self) -> bool:
        return self.params_sigma is not None

    def to_json(self) -> dict:
        from calib3r_graph.io.results import tangent_in_ee_frame

        if not self.propagated:
            return {"propagated": False, "why": NOT_PROPAGATED}
        return {"propagated": True, "params_sigma_px": dict(zip(PARAMS, map(float, self.params_sigma))),
                "source": self.source, "scale_sigma_rel": self.scale_sigma_rel,
                "shift_per_sigma_ee_frame": {p: tangent_in_ee_frame(self.R_ee_cam, xi)
                                             for p, xi in self.shift_per_sigma.items()},
                "data_sigma_px": None if self.data_sigma_px is None else dict(zip(PARAMS, self.data_sigma_px)),
                "data_step_px": None if self.data_step_px is None else dict(zip(PARAMS, self.data_step_px)),
                "model": "Sigma_cam = J Sigma_theta J^T, J = d(ee_T_cam, metric scale)/d(fx, fy, cx, cy) of the "
                         "solved graph (implicit function theorem); the matches' depths are held fixed"}


def parse_intrinsics_sigma(text: str) -> tuple:
    """``"F,C"`` (px) -> (F, F, C, C): the 1-sigma of the focal lengths and of the principal point."""
    try:
        f, c = (float(x) for x in text.split(","))
    except ValueError:
        raise InputError("--intrinsics-sigma-px", f"'{text}' is not F,C (two numbers in px, e.g. 5,4)") from None
    if not (np.isfinite(f) and np.isfinite(c) and f >= 0 and c >= 0):
        raise InputError("--intrinsics-sigma-px", f"'{text}': both sigmas must be finite and >= 0")
    return (f, f, c, c)


def with_params_sigma(ds, sigma: tuple | None, source: str):
    """The dataset with every camera's params_sigma replaced by ``sigma`` (None: unchanged)."""
    if sigma is None:
        return ds
    cameras = {n: dataclasses.replace(c, params_sigma=tuple(sigma)) for n, c in ds.cameras.items()}
    return dataclasses.replace(ds, cameras=cameras, meta={**ds.meta, "params_sigma_source": source})


def _moved(Ks, cameras, cam, p, h) -> dict:
    """The grid intrinsics with camera ``cam``'s parameter ``p`` (index into PARAMS) moved by ``h``
    px of the full image."""
    axis = p % 2
    out = {v: np.array(K, float) for v, K in Ks.items()}
    for v, step in _grid_steps(Ks, cameras, cam, p, h).items():
        out[v][axis, axis if p < 2 else 2] += step
    return out


def _moved_by(o, thetas) -> list:
    """The parameters (indices into thetas) of the cameras of pair ``o``."""
    cams = (split_view_id(o.view_a)[0], split_view_id(o.view_b)[0])
    return [j for j, (c, _, _) in enumerate(thetas) if c in cams]


def pair_sensitivities(lins, values, keys, Ks, noise, thetas, steps) -> list:
    """Each view pair's part of the sensitivities, or None where no parameter moves it (or ``lins``
    has None): (its keys, J^T dE (D, m), dE^T dE (m, m), dE^T e (m,)), with e its whitened
    residual, J its whitened Jacobian and dE the change of e per +1 sigma of each parameter
    (``steps[j][view]``: that sigma on the view's grid), from the pair's factor linearised at
    ``values`` (``lins``: solver.graph.scene_linearisation's keys, kept observations, W, J, e).

    The residual ``e_p = g_a - (s_b / s_a) R_ab g_b - t_ab / s_a`` (factors.match3d, with
    ``g = (1 + phi . c) P`` the corrected lifted point) is affine in the lifted points, so a change
    ``d`` of them changes it by ``(1 + phi_a . c_a) d_a - (s_b / s_a) (1 + phi_b . c_b) R_ab d_b``
    exactly. Points lifted as ``z K^-1 [u, v, 1]`` (``x = (u - cx) z / fx``) change, to first order,
    only in x for fx and cx (``-x h / fx``, ``-z h / fx``) and only in y for fy and cy.

    Written for few numpy calls, as a pair's arrays are small and the calls' overhead was most of
    the cost: what depends on a view alone (its pose, scale, depth correction and each parameter's
    ``-step / focal length``) once per view, R_ab of every pair in one array, and each pair's
    parameters and both its views at once: one product ``C W^T`` gives, per residual row, W's
    column of each parameter's moved coordinate and W R_ab's (b's change rotated into a's frame),
    one multiplication scales them by the lifted points' changes, and dE^T (m, 3n) serves the
    three products. tests/test_camera_model_batch.py checks it against the plain pair-by-pair form
    to 1e-10. On rwhe_kuka_1's live update at 25 frames (135 pairs, 95k matches; CPU time,
    median): 53 ms (pair by pair) -> 33 ms, of which about 14 ms is J^T dE reading J.
    Concatenating all pairs' matches into single passes was slower (37-46 ms): its ~10 MB arrays
    fall out of the cache and page-fault, where one pair's stay in it."""
    out = [None] * len(lins)
    cams = {c for c, _, _ in thetas}
    idx = [i for i, lin in enumerate(lins) if lin is not None
           and {split_view_id(lin[1].view_a)[0], split_view_id(lin[1].view_b)[0]} & cams]
    views = {v for i in idx for v in (lins[i][1].view_a, lins[i][1].view_b)}
    R = {v: values.atPose3(keys.pose(v)).rotation().matrix() for v in views}
    s = {v: values.atDouble(keys.scale(v)) for v in views}
    corr = {v: depth_correction(values, keys, v) for v in views} if noise.depth_correction_sigma > 0 else None
    m, axes = len(thetas), [p % 2 for _, p, _ in thetas]
    coords = [ax if p < 2 else 2 for (_, p, _), ax in zip(thetas, axes)]  # the lifted coordinate each one moves
    # each parameter's -step / focal length (the lifted coordinate's change per unit of it), 0 where the
    # view's camera has no such parameter
    g = {v: np.array([[-st.get(v, 0.0) / Ks[v][ax, ax]] for st, ax in zip(steps, axes)]) for v in views}
    # per pair, the rows of C that pick each parameter's column of W, then of W R_ab
    R_ab = np.array([R[lins[i][1].view_a].T @ R[lins[i][1].view_b] for i in idx]).reshape(-1, 3, 3)
    C = np.concatenate((np.broadcast_to(np.eye(3)[:2], (len(idx), 2, 3)), R_ab[:, :, :2].transpose(0, 2, 1)), 1)
    C = C[:, axes + [2 + ax for ax in axes]]
    buf = np.empty(6 * m * max((len(lins[i][1]) for i in idx), default=0))  # C W^T of every pair (one
    for i, Ci in zip(idx, C):  # allocation: a fresh one per pair page-faulted, 5 % slower)
        k, o, W, J, e = lins[i]
        Q = np.matmul(Ci, W.reshape(-1, 3).T, out=buf[:6 * m * len(o)].reshape(2 * m, -1)).reshape(2 * m, -1, 3)
        x = np.concatenate((o.pts_a.T[coords] * g[o.view_a],
                            o.pts_b.T[coords] * (g[o.view_b] * (-s[o.view_b] / s[o.view_a]))))
        if corr is not None:  # the lifted points' changes times (1 + phi . c)
            x[:m] *= 1 + o.basis_a @ corr[o.view_a]
            x[m:] *= 1 + o.basis_b @ corr[o.view_b]
        Q *= x[:, :, None]
        dE = (Q[:m] + Q[m:]).reshape(m, -1)  # dE^T
        out[i] = (k, (dE @ J).T, dE @ dE.T, dE @ e)
    return out


def _grid_steps(Ks, cameras, cam, p, h) -> dict:
    """{view: how far parameter ``p`` of its grid K moves} when camera ``cam``'s moves by ``h`` px:
    the frontend grid's K is a scaled and shifted copy of the camera's, so h times the grid's scale."""
    axis = p % 2  # fx, cx: x; fy, cy: y
    return {v: h * K[axis, axis] / cameras[cam].K[axis, axis] for v, K in Ks.items() if split_view_id(v)[0] == cam}


def camera_parameters(keys, cameras: dict, Ks) -> tuple[list, list]:
    """(thetas, steps): each (camera, parameter index, 1-sigma px) with a stated sigma, and for
    each the {view: that sigma on the view's grid} that :func:`pair_sensitivities` takes."""
    thetas = [(c, p, float(s)) for c in keys.cameras if cameras[c].params_sigma is not None
              for p, s in enumerate(cameras[c].params_sigma) if s > 0]
    return thetas, [_grid_steps(Ks, cameras, c, p, s) for c, p, s in thetas]


def camera_model_errors(graph, values, keys, observations, weights, Ks, noise, cameras: dict,
                        source: str = "dataset.yaml", system=None, terms=None) -> dict:
    """{camera: CameraModelError} of a solved graph.

    ``observations``, ``weights``, ``Ks``, ``noise``: what the 3D match factors of ``graph``
    were built from (solver.graph.add_scene_factors); ``cameras``: {name: Camera} with
    ``params_sigma`` (px) or None. Given ``system`` ((H, offsets) of ``graph`` at ``values``), it is
    not linearised again; ``terms``: each pair's :func:`pair_sensitivities` at ``values`` with the parameters of
    :func:`camera_parameters`, where the caller linearised the pairs itself. H and the pairs' terms
    must come from one linearisation point: on rwhe_kuka_1's live updates, H from before a
    Gauss-Newton step with terms from after it put the share off by up to 700x (the sum over pairs
    cancels to a small remainder that only a consistent H leaves small).
    """
    thetas, steps = camera_parameters(keys, cameras, Ks)
    out = {c: CameraModelError(np.zeros((6, 6)), 0.0, None, "", {}, None) for c in keys.cameras}
    for c in keys.cameras:  # given but all zero: propagated, and nothing to add
        if cameras[c].params_sigma is not None:
            out[c] = CameraModelError(np.zeros((6, 6)), 0.0, tuple(map(float, cameras[c].params_sigma)), source, {},
                                      [float("inf")] * 4)
    if not thetas:
        return out
    H, offsets = system[:2] if system is not None else linear_system(graph, values)[:2]
    n, mm = H.shape[0], len(thetas)
    G, info, grad = np.zeros((n, mm)), np.zeros((mm, mm)), np.zeros(mm)
    if terms is None:  # linearised here, a chunk of pairs at a time (their Jacobians held together)
        terms = []
        for i in range(0, len(observations), 64):
            lins = [scene_linearisation(o, w, values, keys, Ks, noise) if _moved_by(o, thetas) else None
                    for o, w in zip(observations[i:i + 64], weights[i:i + 64])]
            terms += pair_sensitivities(lins, values, keys, Ks, noise, thetas, steps)
    for t in terms:
        if t is None:
            continue
        k, JdE, dEdE, dEe = t
        row = 0
        for key in k:
            a, d = offsets[key]
            G[a:a + d] += JdE[row:row + d]
            row += d
        info += dEdE
        grad += dEe
    HiG = np.linalg.solve(H, G)
    dx = -HiG  # (n, m): the solution's move for +1 sigma of each parameter (implicit function theorem)
    reduced = info - G.T @ HiG  # the scene's information on theta, the rest of the graph free (Schur complement)
    sig = np.array([t[2] for t in thetas])
    try:
        data_sigma = np.sqrt(np.maximum(np.diag(np.linalg.inv(reduced)), 0)) * sig
        data_step = -np.linalg.solve(reduced, grad) * sig  # what refining theta in the graph would do (one GN step)
    except np.linalg.LinAlgError:
        data_sigma, data_step = np.full(mm, np.inf), np.zeros(mm)
    for c in keys.cameras:
        e, s_key = keys.hand_eye(c), keys.metric(c)
        a, d = offsets[e]
        X = dx[a:a + d]
        lam = values.atDouble(s_key)
        scale = dx[offsets[s_key][0]] / lam if s_key in offsets else np.zeros(mm)
        mine = [j for j, t in enumerate(thetas) if t[0] == c]
        data, step = [float("inf")] * 4, [0.0] * 4
        for j in mine:
            data[thetas[j][1]], step[thetas[j][1]] = float(data_sigma[j]), float(data_step[j])
        given = out[c].params_sigma
        out[c] = CameraModelError(X @ X.T, float(np.sqrt(scale @ scale)), given, source if given else "",
                                  {PARAMS[thetas[j][1]]: X[:, j] for j in mine}, data if given else None,
                                  values.atPose3(e).rotation().matrix(), step if given else None)
    return out


# Below these a share is not worth a warning (the same limits as uncertainty.covariance_diagnostics)
WEAK_MM, WEAK_DEG = 2.0, 0.2


def dominance(camera, T_ee_cam, rest, err) -> str | None:
    """A warning when the camera model's share is the larger part of a sigma above WEAK_MM /
    WEAK_DEG: more robot poses will not shrink it, better intrinsics will."""
    from calib3r_graph.io.results import uncertainty_report

    if not err.propagated:
        return None
    cam = uncertainty_report(T_ee_cam, err.covariance)["sigma_ee_frame"]
    other = uncertainty_report(T_ee_cam, rest)["sigma_ee_frame"]
    worst = [(a, cam[a], lim) for a, lim in (("x_mm", WEAK_MM), ("y_mm", WEAK_MM), ("z_mm", WEAK_MM),
                                             ("rx_deg", WEAK_DEG), ("ry_deg", WEAK_DEG), ("rz_deg", WEAK_DEG))
             if np.hypot(cam[a], other[a]) > lim and cam[a] > other[a]]
    if not worst:
        return None
    axes = ", ".join(f"{a.split('_')[0]} {v:.2f} {a.split('_')[1]}" for a, v, _ in worst)
    given = " ".join(f"{x:.2g}" for x in err.params_sigma)
    return (f"{camera}: the intrinsics' uncertainty (fx fy cx cy ± {given} px) is the larger part of the sigma "
            f"({axes} of ee_T_cam from the camera model alone): calibrate the intrinsics more precisely (a board "
            "in many images, tilted and covering the corners) rather than adding robot poses")


def add_camera_model(sol, ds, weights, Ks, noise, at=None, **shared):
    """Add each camera's camera-model share to ``sol``'s total covariance and metric-scale sigma,
    after the jackknife's cover (the leave-one-out solves share the intrinsics, so their spread
    holds none of it); ``sol.stats["camera_model"]`` records it. ``at``: the values the
    share is linearised at (default ``sol.values``); ``shared``: :func:`camera_model_errors`'
    ``system`` or ``terms`` at those values (a live update's Gauss-Newton step
    linearised before it moved: its H and its pairs' terms are both from there)."""
    t = time.perf_counter()
    graph = sol.graph if shared.get("system") is None else None  # (a live update's: built only where asked)
    cm = camera_model_errors(graph, sol.values if at is None else at, sol.keys, sol.observations, weights, Ks, noise,
                             {c: ds.cameras[c] for c in sol.keys.cameras},
                             ds.meta.get("params_sigma_source", "dataset.yaml"), **shared)
    for c, err in cm.items():
        msg = dominance(c, sol.ee_T_cam[c], np.asarray(sol.covariance[c]), err)
        if msg:
            log.warning("%s", msg)
            sol.diagnostics.append(msg)
        sol.covariance[c] = np.asarray(sol.covariance[c]) + err.covariance
        lam, sigma = sol.metric_scale[c]
        sol.metric_scale[c] = (lam, float(np.hypot(sigma, lam * err.scale_sigma_rel)))
    sol.camera_model = cm
    sol.stats["camera_model"] = {c: e.to_json() for c, e in cm.items()}
    sol.stats["timings_s"]["camera_model"] = time.perf_counter() - t
    return cm


def with_moved_intrinsics(ds, preds, camera: str, param: str, delta_px: float):
    """(dataset, predictions) with ``camera``'s ``param`` (fx, fy, cx or cy) moved by ``delta_px``
    (full-image px) in dataset.yaml's camera and in every one of its views' grid K: what solving
    with other intrinsics means when the depths do not depend on K (a depth sensor, the
    simulator). For checking the linearisation against a re-solve."""
    from calib3r_graph.io.predictions import Predictions

    p = PARAMS.index(param)
    cam = ds.cameras[camera]
    params = list(cam.params)
    params[p] += delta_px
    ds2 = dataclasses.replace(ds, cameras={**ds.cameras, camera: dataclasses.replace(cam, params=tuple(params))})
    Ks = _moved({v: vp.K for v, vp in preds.views.items()}, ds.cameras, camera, p, delta_px)
    views = {v: dataclasses.replace(vp, K=Ks[v]) for v, vp in preds.views.items()}
    return ds2, Predictions(preds.name, preds.info, views, preds.pairs)
