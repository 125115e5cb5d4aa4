"""Readers for the files robots, cameras and ROS write (pose files, intrinsics files, bags).

A lower layer: it imports only calib3r_graph's dataset, errors, output and boards modules."""
