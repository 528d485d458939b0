"""
Rosbag2 tools: a MRCLAM dataset as a bag, and a recorded bag through the pipeline offline.

This layer converts messages (it imports rclpy's serialisation and the message
packages); the bag files themselves are read and written with ``rosbags`` (raw CDR), so
the package's own codecs in ``landmark_ros.ros`` are used unchanged.

``storage``
    Open a bag with one-line errors; write one atomically (temporary directory, rename).
``params``
    Node sections of a ROS parameter file, matched on the fully qualified node name.
``export``
    ``export_dataset``: a MRCLAM dataset as the observers' inputs plus ground truth.
``process``
    ``process_bag``: per robot an ``Observer``, one ``Fuser``, on bag time.
``cli``
    The ``landmark_bag`` console script.
"""
