"""A view pair's linearised 3D match factor, kept across live updates while it still holds.

What GTSAM's iSAM2 calls fluid relinearisation, for the live engine's hand-built linear system
(``update.UpdateContext.linear_system``). A pair's factor depends only on its two views' relative pose,
depth scales and corrections, and its weights. Between two updates at 15-30 poses the old pairs'
relative poses move by 1-4e-4 rad and 5e-4-1e-3 of their baseline, their depth scales by
1e-4-8e-4 (rwhe_kuka_1, a random order, medians per update), so their Jacobians are the same to a
few parts in 10^4, and recomputing them was most of an update (the linearisation 0.13 s and the
camera-model terms 0.06 s of about 0.42 s at 25 frames).

A pair linearised at ``x0`` with weights ``w0`` (``A = J``, ``b = -e``: ``A^T A``, ``A^T b``,
``b^T b``) is reused at ``x = x0 + delta`` as the same linear factor moved there (iSAM2's linear
prediction, ``b' = b - A delta``, as :func:`solver.jackknife.moved_system`), times ``scale /
scale0`` (the noise calibration's ``1 / (sigma0^2 kappa)``, which every whitened row carries as a
square root), while

- its observations and the two point sigmas of its whitening are the same;
- below ``engine.KEEP_WEIGHTS_FROM`` poses, the weights given now are within ``WEIGHT_TOL`` of ``w0``
  (``sum |w - w0| <= WEIGHT_TOL sum w0``): the factor then holds the pair's information to that
  fraction. From there on it keeps ``w0``, robust weights lagged by the updates it is kept for, as
  every update's are lagged by one (the engine's comment on ``KEEP_WEIGHTS_FROM`` gives the
  measurements);
- the linear model predicts an rms change of the pair's whitened match residuals since ``x0`` below
  ``DRIFT_SIGMAS`` (``delta^T A^T A delta <= DRIFT_SIGMAS^2 n``, n its matches of non-zero weight):
  a relative motion of about ``DRIFT_SIGMAS`` depth sigmas (1 %), so the Jacobian is right to a few
  parts in 10^3.

On rwhe_kuka_1 (a random order, seed 0) 2088 kept factors were offered: 1067 failed the weights
rule (the median weights had moved by 1.2 % since ``x0``), 21 the drift rule (median drift 0.11),
206 had new observations, and 794 were reused (with the weights rule at every pose count, before
``KEEP_WEIGHTS_FROM``). What the kept factor misses is the part of the
pair's nonlinearity its motion since ``x0`` brings: after a large step the factor anew shows a
remainder the kept one cannot (up to 0.2 sigma of a view's variable on the simulator's replay), which
the pair's next relinearisation takes up.

Only an update's first step reuses (``update.UpdateContext.fresh``): a later step of the same update, the
re-weighted second step or a re-run of ``solve``'s schedule, follows a large move, where a factor
linearised before it predicts least well, and the schedule is to give ``solve``'s result (a re-run
with kept factors ended 0.14 sigma from it on the simulator, where the test allows 0.1).

The camera-model terms (``camera_model.pair_sensitivities``: ``J^T dE``, ``dE^T dE``, ``dE^T e``) move
the same way: ``dE^T e' = dE^T e + (J^T dE)^T delta``. Everything else of an update (residuals,
weights, the noise calibration, the step's cost check) is computed exactly at every update, and
``Engine.finish`` is ``solve`` itself. What this changes in the updates, and saves, is measured in
docs/live-notes.md.
"""

from dataclasses import dataclass

import gtsam
import numpy as np

from calib3r_graph.solver.graph import depth_correction

WEIGHT_TOL = 0.01
DRIFT_SIGMAS = 0.2


@dataclass
class PairLinearisation:
    """One pair's linear factor at ``x0``, columns in its keys' order (pose a, pose b, scale a,
    scale b[, correction a, correction b]), whitened with weights ``w0`` and scale ``scale0``."""
    obs: object
    sigmas: tuple
    x0: tuple  # (base_T_a, base_T_b, s_a, s_b, c_a, c_b) at the linearisation
    w0: np.ndarray
    scale0: float
    AtA: np.ndarray
    Atb: np.ndarray
    btb: float
    term: tuple | None = None  # (J^T dE, dE^T dE, dE^T e) of camera_model.pair_sensitivities at x0, () if none

    def moved(self, o, w, scale, sigmas, values, keys, with_correction: bool, weight_tol: float | None):
        """(A^T A, A^T b, b^T b, delta, scale / scale0) of this factor moved to ``values``, or None
        where it no longer holds (the module's three rules). ``weight_tol``: the weights rule's bound
        (``WEIGHT_TOL``, as the caller reads it; None: its weights ``w0`` are kept whatever the weights
        given now, as from ``engine.KEEP_WEIGHTS_FROM`` poses)."""
        if o is not self.obs or sigmas != self.sigmas or len(w) != len(self.w0):
            return None
        total = float(self.w0.sum())
        if not total > 0 or (weight_tol is not None and float(np.abs(w - self.w0).sum()) > weight_tol * total):
            return None
        delta = _delta(self.x0, point(o, values, keys, with_correction))
        if len(delta) != len(self.Atb) or \
                float(delta @ self.AtA @ delta) > DRIFT_SIGMAS**2 * int((self.w0 > 0).sum()):
            return None
        r = scale / self.scale0
        Atb = self.Atb - self.AtA @ delta
        return (r * self.AtA, r * Atb, r * (self.btb - 2 * delta @ self.Atb + delta @ self.AtA @ delta), delta, r)

    def moved_term(self, delta, r):
        """The camera-model terms moved by ``delta`` and rescaled by ``r``; None where no parameter
        moves the pair."""
        if not self.term:
            return None
        JtdE, dEtdE, dEte = self.term
        return r * JtdE, r * dEtdE, r * (dEte + JtdE.T @ delta)


def point(o, values, keys, with_correction: bool) -> tuple:
    """The pair's variables at ``values``: (base_T_a, base_T_b, s_a, s_b, c_a, c_b)."""
    a, b = o.view_a, o.view_b
    c = (depth_correction(values, keys, a), depth_correction(values, keys, b)) if with_correction else (None, None)
    return (values.atPose3(keys.pose(a)), values.atPose3(keys.pose(b)), values.atDouble(keys.scale(a)),
            values.atDouble(keys.scale(b))) + c


def _delta(x0, x) -> np.ndarray:
    """The tangent vector from ``x0`` to ``x`` in the factor's column order (gtsam's retract)."""
    parts = [gtsam.Pose3.localCoordinates(x0[0], x[0]), gtsam.Pose3.localCoordinates(x0[1], x[1]),
             [x[2] - x0[2]], [x[3] - x0[3]]]
    if x[4] is not None:
        parts += [np.asarray(x[4]) - np.asarray(x0[4]), np.asarray(x[5]) - np.asarray(x0[5])]
    return np.concatenate([np.asarray(p, float).ravel() for p in parts])
