"""ROS-free pipeline: the observer and fuser logic as objects (numpy, scipy)."""
