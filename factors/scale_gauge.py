"""A camera's metric scale as the geometric mean of its views' depth scales.

Each view v of camera j has a depth scale s_v (metres per frontend depth unit);
the camera's metric scale lambda_j is defined by

    e = log(lambda_j) - mean_v log(s_v)          (1,: dimensionless, log-scale)

held with a tight noise model, so lambda_j is a variable whose marginal gives
the scale's uncertainty while the per-view scales keep their freedom.
Keys: ``[lambda_j, s_1, ..., s_n]`` (all doubles).
"""

from functools import partial

import gtsam
import numpy as np


def scale_gauge_error(_unused, this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
    keys = this.keys()
    lam = values.atDouble(keys[0])
    s = np.array([values.atDouble(k) for k in keys[1:]])
    n = len(s)
    if jacobians is not None:
        jacobians[0] = np.array([[1.0 / lam]])
        for i, s_i in enumerate(s):
            jacobians[i + 1] = np.array([[-1.0 / (n * s_i)]])
    # A trial step of LM may take a scale to zero or below: the error is then NaN, without numpy's
    # RuntimeWarning on the user's terminal, and LM rejects the step (a NaN cost is never lower), so
    # the scales stay positive from their positive start (solver/init.py refuses any other).
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.array([np.log(lam) - np.mean(np.log(s))])


def make_scale_gauge_factor(keys, noise) -> gtsam.CustomFactor:
    return gtsam.CustomFactor(noise, list(keys), partial(scale_gauge_error, None))
