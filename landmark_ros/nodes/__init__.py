"""Thin rclpy nodes: message -> arrays -> pipeline -> message -> publish."""

import sys

if sys.argv[:1] == ['-m']:
    # ``python -m landmark_ros.nodes.NAME``: Python is still locating the module
    # (sys.argv[0] is '-m' until then). A SIGINT during the node's imports ends it
    # with exit code 0, as with the console scripts (``start``).
    from landmark_ros.nodes import start
    start.install()
