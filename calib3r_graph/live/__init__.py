"""Live, guided calibration: an incremental engine over frames arriving one at a time, the total
sigma at every update, the next poses to record, and a stop rule (docs/live.md)."""

from calib3r_graph.live.session import LiveSession, Update

__all__ = ["LiveSession", "Update"]
