"""Shared by the observer, the fuser and the localizer: config, counters, row checks, pose buffer (ROS-free)."""
