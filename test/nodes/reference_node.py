"""
A plain rclpy node with the observer's endpoints and nothing else: the reference start.

It imports only rclpy and std_msgs, so the seconds until its endpoints are in the graph
are the floor that DDS start and discovery set for any Python node on this machine
(``startup.py`` prints it beside the package's nodes). Ends with exit code 0 on SIGINT.
"""

import signal
import sys


def main():
    """Create the endpoints, spin until SIGINT or SIGTERM."""
    signal.signal(signal.SIGINT, lambda *_: sys.exit(0))
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    import rclpy
    from std_msgs.msg import Empty
    rclpy.init()
    node = rclpy.create_node('rclpy_reference')
    for topic in ('pose', 'observations'):
        node.create_subscription(Empty, topic, lambda msg: None, 10)
    for topic in ('landmarks', 'partial_observations', 'landmark_markers', '/diagnostics'):
        node.create_publisher(Empty, topic, 10)
    try:
        rclpy.spin(node)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
