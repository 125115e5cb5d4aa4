"""Dense metric reconstruction after a solve, on the CPU: per-view depth from the solved poses (rectified
pairs matched with OpenCV's semi-global matcher, kept where several views agree), or the dataset's own
dense depth (sensor depth, a foundation model's predictions); fused with Open3D's TSDF into one cloud
and one mesh in the robot's base frame; and the cross-view surface disagreement under the robot's chain
``base_T_ee · ee_T_cam``, a check of the hand-eye that needs no board. See docs/dense.md."""

from calib3r_graph.dense.run import DenseOptions, reconstruct, reconstruct_result

__all__ = ["DenseOptions", "reconstruct", "reconstruct_result"]
