"""ROS-free simulator of a team of robots observing landmarks."""
