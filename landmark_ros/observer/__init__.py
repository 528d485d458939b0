"""The observer: observation rows to world-frame landmarks and partial observations (ROS-free)."""
