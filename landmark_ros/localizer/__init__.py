"""
The localizer: a robot's pose from odometry and landmark sightings (ROS-free).

``motion`` (odometry motion and its noise), ``update`` (the EKF update against the map and
other robots), ``config`` (``LocalizerConfig``), ``localizer`` (``Localizer``, the pipeline
object the node, the MRCLAM replay and the tests drive).
"""
