"""Systematic robot error that per-pose noise cannot represent, estimated from the data.

A real arm's pose error is not independent from pose to pose: kinematic miscalibration (link
lengths, joint offsets) gives an error that varies smoothly across the workspace. Independent
per-pose noise averages out over n poses; a smooth field does not, and part of it is
indistinguishable from a change of ``ee_T_cam`` or of the metric scale, so the marginal
covariance of the noise model cannot show it.

Model (first order): the flange's position error at pose i is ``delta_i = L (p_i - p_mean) + w_i``
and its orientation error (base frame) ``phi_i = M (p_i - p_mean) + u_i``, with ``p_i`` the flange
position (a proxy for the arm's configuration), ``L`` and ``M`` 3x3 gradients whose entries are
i.i.d. N(0, tau_t^2) (m per m) and N(0, tau_r^2) (rad per m), and ``w_i``, ``u_i`` white.

**Measuring tau** (:func:`measure_field`). The linearised absolute AX = XB,

    position:     R_ee,i t_X - w - s c_i = -t_ee,i - delta_i     unknowns [t_X (ee frame), w, s]
    orientation:  rho_i = omega_w + R_ee,i theta_X + phi_i        unknowns [theta_X, omega_w]

(``c_i`` the solved camera centre, ``rho_i`` the flange orientation measured against the solved
one), leaves ``(I - J J^+)`` of the field in the residual: that part of it the unknowns cannot
absorb. tau^2 is measured there by the method of moments, the white part from the rest of the
residual.

**Propagating it** (:func:`propagate`). The whole field, including the part that looks exactly
like a scale or a hand-eye change, goes through the solver's own linearised graph: a flange
perturbation ``xi`` (body frame) changes the robot pose factor's error by ``-Ad(C^-1 E) xi``; the
solution moves by ``dx = (A^T A)^-1 A^T db`` for each of the 36 field directions, and
``Sigma = sum_k tau_k^2 dx_k dx_k^T``. So its effect on the rotation, on the other cameras of a
rig and on the scale is included. With white robot noise, as in the simulator, tau is about 0
and nothing is added.
"""

from dataclasses import dataclass

import numpy as np

FIELD_MIN_POSES = 8  # below this the field is not measured (taken as zero; solve's jackknife covers it)


@dataclass
class SystematicError:
    covariance: np.ndarray  # 6x6 on ee_T_cam's tangent [w, v] (rad, m)
    scale_sigma_rel: float  # relative sigma it adds to the metric / board scale
    tau: np.ndarray  # [[position m/m, m/rad], [orientation rad/m, rad/rad]]: rms of a gradient entry
    white_mm: float  # per-axis sigma of the white part of the position residual
    poses: int

    @property
    def measured(self) -> bool:
        """False when there were too few poses to measure the field (it is then taken as zero)."""
        return bool(np.isfinite(self.white_mm))

    @property
    def gradient_mm_per_m(self) -> float:
        return float(self.tau[0, 0] * 1e3)

    @property
    def gradient_deg_per_m(self) -> float:
        return float(np.degrees(self.tau[1, 0]))

    def to_json(self) -> dict:
        t = np.asarray(self.tau)
        return {"position_mm_per_m": float(t[0, 0] * 1e3), "position_mm_per_deg": float(t[0, 1] * 1e3 * np.pi / 180),
                "orientation_deg_per_m": float(np.degrees(t[1, 0])), "orientation_deg_per_deg": float(t[1, 1]),
                "white_mm": self.white_mm if self.measured else None, "measured": self.measured,
                "scale_sigma_rel": self.scale_sigma_rel, "poses": self.poses,
                "model": "flange position and orientation errors linear in the flange's position and orientation "
                         "(a kinematic error), measured from the robot residuals, propagated through the solved graph"}


def flange_configuration(base_T_cam: list, ee_T_cam) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) flange positions (m) and (n, 3) orientations (rotation vectors about the mean
    orientation, rad) of the solution, base_T_cam * ee_T_cam^-1: a proxy for the arm's joint
    configuration (the measured poses carry the very noise being measured)."""
    return configuration([C.compose(ee_T_cam.inverse()) for C in base_T_cam])


def configuration(base_T_flange: list) -> tuple[np.ndarray, np.ndarray]:
    import gtsam

    p = np.array([F.translation() for F in base_T_flange])
    R0 = base_T_flange[0].rotation()
    w = np.array([gtsam.Rot3.Logmap(R0.between(F.rotation())) for F in base_T_flange])
    R_mean = R0.compose(gtsam.Rot3.Expmap(w.mean(axis=0)))
    return p, np.array([gtsam.Rot3.Logmap(R_mean.between(F.rotation())) for F in base_T_flange])


def field_basis(x: np.ndarray) -> np.ndarray:
    """(3n, 9): the error of every pose for each entry of a 3x3 gradient (row-major) over x (n, 3)."""
    cc = x - x.mean(axis=0)
    return np.einsum("ab,nc->nabc", np.eye(3), cc).reshape(3 * len(x), 9)


def _moments(r: np.ndarray, J: np.ndarray, Phis: list) -> tuple[list, float]:
    """([tau_j], white sigma) of ``r = J theta + sum_j Phi_j vec(G_j) + white``, vec(G_j) ~ N(0, tau_j^2 I),
    by the method of moments: E[r'^T A r'] = sum_j tau_j^2 tr(Q_j^T A Q_j) + s^2 tr(A M) for the
    residual r' = M r, M = I - J J^+, Q_j = M Phi_j, with A the projector onto each Q_j and A = I."""
    P = np.linalg.pinv(J)
    M = np.eye(len(r)) - J @ P
    resid = M @ r
    Qs = [M @ Phi for Phi in Phis]
    projectors = []
    for Q in Qs:
        U, sv, _ = np.linalg.svd(Q, full_matrices=False)
        projectors.append(U[:, :int(np.sum(sv > 1e-9 * max(sv[0], 1e-300)))])
    As = [(lambda x, U=U: U @ (U.T @ x)) for U in projectors] + [lambda x: x]
    lhs = np.array([[np.sum(Q * A(Q)) for Q in Qs] + [np.trace(M) if A is As[-1] else U.shape[1]]
                    for A, U in zip(As, projectors + [None])])
    rhs = np.array([resid @ A(resid) for A in As])
    active = list(range(len(Qs)))
    while True:  # non-negative: drop a component that comes out negative and solve again
        idx = active + [len(Qs)]
        sol = np.linalg.lstsq(lhs[np.ix_(idx, idx)], rhs[idx], rcond=None)[0]
        if np.all(sol[:-1] >= 0) or not active:
            break
        active.pop(int(np.argmin(sol[:-1])))
    tau2 = np.zeros(len(Qs))
    tau2[active] = sol[:-1]
    return [float(np.sqrt(t)) for t in tau2], float(np.sqrt(max(sol[-1], 0.0)))


def measure_field(base_T_ee: list, base_T_cam: list, ee_T_cam) -> tuple[np.ndarray, float]:
    """(tau, white): tau = [[position error per m, per rad], [orientation error per m, per rad]] of
    the flange (m/m, m/rad; rad/m, rad/rad), and the white position sigma (m), from one camera's
    robot poses. ``base_T_ee[i]`` (measured) and ``base_T_cam[i]`` (solved) are the same pose i."""
    import gtsam

    n = len(base_T_ee)
    if n < FIELD_MIN_POSES:  # 7 unknowns and 2 x 9 field directions need more residual than this
        return np.zeros((2, 2)), float("nan")
    R_ee = np.array([E.rotation().matrix() for E in base_T_ee])
    t_ee = np.array([E.translation() for E in base_T_ee])
    c = np.array([C.translation() for C in base_T_cam])
    p, w = flange_configuration(base_T_cam, ee_T_cam)
    Phis = [field_basis(p), field_basis(w)]
    r = (t_ee + R_ee @ ee_T_cam.translation() - c).ravel()  # robot chain minus solved camera centre (m)
    J = np.zeros((3 * n, 7))
    J[:, :3] = R_ee.reshape(3 * n, 3)
    J[:, 3:6] = -np.tile(np.eye(3), (n, 1))
    J[:, 6] = -c.ravel()
    tau_t, white = _moments(r, J, Phis)
    R_x = ee_T_cam.rotation()
    rho = np.concatenate([gtsam.Rot3.Logmap(E.rotation().compose(C.rotation().compose(R_x.inverse()).inverse()))
                          for E, C in zip(base_T_ee, base_T_cam)])  # measured vs solved flange orientation
    J_r = np.hstack([np.tile(np.eye(3), (n, 1)), R_ee.reshape(3 * n, 3)])
    tau_r, _ = _moments(rho, J_r, Phis)
    return np.array([tau_t, tau_r]), white


def _dim(values, key) -> int:
    for get, dim in ((values.atPose3, lambda v: 6), (values.atDouble, lambda v: 1),
                     (values.atVector, lambda v: len(v))):
        try:
            return dim(get(key))
        except RuntimeError:
            continue
    raise ValueError(f"unsupported value type for key {key}")


_LAST_SYSTEM = []  # [(graph, values, sizes, result)]: solve asks twice for one (here and camera_model.py)


def linear_system(graph, values) -> tuple[np.ndarray, dict, object]:
    """(H, {key: (column, dim)}, the linearised graph) at ``values``: H = A^T A of the whole
    graph (Gauss-Newton), dense, in sorted key order (every tangent in GTSAM's local coordinates).
    The last one is kept: the same graph and values objects give it again without linearising."""
    sizes = (graph.size(), values.size())
    if _LAST_SYSTEM and _LAST_SYSTEM[0][0] is graph and _LAST_SYSTEM[0][1] is values and _LAST_SYSTEM[0][2] == sizes:
        return _LAST_SYSTEM[0][3]
    _LAST_SYSTEM[:] = [(graph, values, sizes, _linear_system(graph, values))]
    return _LAST_SYSTEM[0][3]


def key_offsets(graph, values) -> dict:
    """{key: (first column, dimension)} of the graph's variables in sorted key order: the column
    layout of every dense information matrix built here (values may hold variables no factor uses)."""
    offsets, col = {}, 0
    for k in sorted(graph.keys()):
        offsets[k] = (col, _dim(values, k))
        col += offsets[k][1]
    return offsets


def _linear_system(graph, values):
    import gtsam

    offsets, ordering = key_offsets(graph, values), gtsam.Ordering()
    for k in offsets:
        ordering.push_back(k)
    lin = graph.linearize(values)
    H, _ = lin.hessian(ordering)  # A^T A, without forming the (tall) dense A
    return H, offsets, lin


def propagate(graph, values, robot: list, tau: np.ndarray, out_keys: list, system=None) -> dict:
    """{key: covariance block} of the fields through the whole linearised graph.

    ``robot``: (ee_T_cam key, base_T_cam key, measured base_T_ee) of every robot pose factor
    ``e = Log((base_T_ee ee_T_cam)^-1 base_T_cam)`` in ``graph``; ``tau`` as measure_field gives it.
    ``system``: (H, offsets) of ``graph`` already linearised (key_offsets' layout); then only the
    robot factors are linearised here.
    """
    if system is None:
        H, offsets, lin = linear_system(graph, values)
        jacobian = lambda i: lin.at(i).jacobian()[0]  # noqa: E731
    else:
        (H, offsets), lin = system, None
        jacobian = lambda i: graph.at(i).linearize(values).jacobian()[0]  # noqa: E731
    index = {tuple(graph.at(i).keys()): i for i in range(graph.size())}
    C = [values.atPose3(c) for _, c, _ in robot]
    # One field for the arm, over every robot pose's flange configuration (any camera's ee_T_cam).
    p, w = configuration([T.compose(values.atPose3(e).inverse()) for (e, _, _), T in zip(robot, C)])
    Phis = [field_basis(p), field_basis(w)]
    g = np.zeros((H.shape[0], 36))  # A^T db: only the robot factors' rows of b change
    for n, ((e, c, E), T) in enumerate(zip(robot, C)):
        i = index[(e, c)]
        model = graph.at(i).noiseModel()
        Ad = T.inverse().compose(E).AdjointMap()
        Rt = E.rotation().matrix().T
        # column 18 kind + 9 b + k: field b's k-th basis vector f as a position (kind 0: xi = [0; f]) or an
        # orientation (kind 1: xi = [f; 0]) offset; b = -whitened error, de = -Ad xi
        F = np.hstack([Rt @ Phi[3 * n:3 * n + 3, :9] for Phi in Phis])  # (3, 18)
        xi = np.zeros((6, 36))
        xi[3:, :18], xi[:3, 18:] = F, F
        db = model.Whiten(Ad @ xi)
        factor = graph.at(i)
        A_i = jacobian(i)
        col = 0
        for key in factor.keys():
            a, d = offsets[key]
            g[a:a + d] += A_i[:, col:col + d].T @ db
            col += d
    dx = np.linalg.solve(H, g) * np.repeat([tau[0, 0], tau[0, 1], tau[1, 0], tau[1, 1]], 9)
    return {k: dx[offsets[k][0]:offsets[k][0] + offsets[k][1]] @ dx[offsets[k][0]:offsets[k][0] + offsets[k][1]].T
            for k in out_keys}


def systematic_errors(graph, values, robot: list, cameras: dict, system=None) -> dict:
    """{camera: SystematicError} for a solved graph.

    ``robot``: (ee_T_cam key, base_T_cam key, measured base_T_ee) of every robot pose factor (one
    arm, one field). ``cameras``: {camera: (ee_T_cam key, scale key or None)}; the scale's sigma
    is reported relative to its value.
    """
    by_ee = {}
    for e, c, E in robot:
        by_ee.setdefault(e, []).append((c, E))
    taus, whites, counts = [], [], []
    for e, items in by_ee.items():
        tau, white = measure_field([E for _, E in items], [values.atPose3(c) for c, _ in items], values.atPose3(e))
        taus.append(tau)
        whites.append(white)
        counts.append(len(items))
    tau = np.sqrt(np.average(np.square(taus), axis=0, weights=counts)) if taus else np.zeros((2, 2))
    whites = [w for w in whites if np.isfinite(w)]
    white = float(np.mean(whites)) if whites else float("nan")
    out_keys = [k for e, s in cameras.values() for k in (e, s) if k is not None]
    blocks = propagate(graph, values, robot, tau, out_keys, system) if tau.sum() > 0 else {}
    out = {}
    for cam, (e, s) in cameras.items():
        scale_rel = float(np.sqrt(blocks[s][0, 0]) / abs(values.atDouble(s))) if s is not None and s in blocks else 0.0
        out[cam] = SystematicError(blocks.get(e, np.zeros((6, 6))), scale_rel, tau, white * 1e3, len(robot))
    return out
