"""What the observer, the fuser and the localizer share: config, counters, rows (ROS-free)."""
