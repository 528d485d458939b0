"""The fuser: sources, tracks, partial observations, publishing schedule, map file (ROS-free)."""
