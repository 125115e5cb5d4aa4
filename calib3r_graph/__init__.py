"""calib3r-graph: joint hand-eye calibration and metric 3D reconstruction on GTSAM."""

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
