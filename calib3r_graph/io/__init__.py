"""Files in and out: the dataset and predictions formats, calibration boards, atomic output,
solve's result files and their export, and readers for the files robots, cameras and ROS write
(pose files, intrinsics files, bags).

A lower layer: it imports only its own modules, calib3r_graph.errors and factors."""
