"""The observer's markers and diagnostics arrive at the configured rates (within 5 %)."""

import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.nodes.observer import LandmarkObserver
from landmark_ros.ros.conversions import stamp_ns
from landmark_ros.ros.schemas import observation_message
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rosutil import header, pose_message, wait_for_match
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

MEASURE_S = 4.0
TOLERANCE = 0.05
INPUT_PERIOD_S = 0.02


def rate(times):
    """Return the rate of events at ``times`` [s]: intervals per second between first and last."""
    times = np.sort(np.asarray(times))
    return (len(times) - 1) / (times[-1] - times[0])


@pytest.mark.parametrize('marker_rate_hz, diagnostics_period_s, max_wait_s', [
    (5.0, 1.0, 0.5),      # the defaults
    (7.0, 0.5, 0.5),      # the diagnostics period is no multiple of the tick period
    (2.0, 0.3, 0.25),
])
def test_markers_and_diagnostics_arrive_at_the_configured_rates(
        env, marker_rate_hz, diagnostics_period_s, max_wait_s):
    params = {'marker_rate_hz': marker_rate_hz, 'diagnostics_period_s': diagnostics_period_s,
              'max_wait_s': max_wait_s}
    node = env.add(LandmarkObserver(
        context=env.context, namespace='/rates',
        parameter_overrides=[Parameter(k, value=v) for k, v in params.items()]))
    name = node.get_fully_qualified_name()
    tester = env.node('tester')
    pose_pub = tester.create_publisher(PoseWithCovarianceStamped, '/rates/pose', 10)
    observation_pub = tester.create_publisher(PointCloud2, '/rates/observations', 10)
    markers, diagnostics = [], []
    tester.create_subscription(MarkerArray, '/rates/landmark_markers',
                               lambda msg: markers.append(time.monotonic()), 10)
    tester.create_subscription(
        DiagnosticArray, '/diagnostics',
        lambda msg: diagnostics.extend(stamp_ns(msg.header.stamp) * 1e-9 for s in msg.status
                                       if s.name == name), 10)
    assert wait_for_match(env, [pose_pub, observation_pub, node.marker_pub], [], 10.0)
    pose_pub.publish(pose_message(10.0, (1.0, 2.0, 0.5), np.eye(3) * 1e-3))
    assert env.spin_until(lambda: len(node.observer.poses) == 1, 10.0)

    # Observations of one landmark keep coming, so every marker tick has something to show.
    cloud = observation_message(header(10.0, 'laser'), [7], [(4.0, 0.7)])
    tester.create_timer(INPUT_PERIOD_S, lambda: observation_pub.publish(cloud))
    assert env.spin_until(lambda: markers and diagnostics, 10.0)
    start = time.monotonic()
    env.spin_for(MEASURE_S)
    markers = [t for t in markers if t >= start]
    diagnostics_stamps = [t for t in diagnostics if t >= diagnostics[0]]

    assert abs(rate(markers) / marker_rate_hz - 1.0) < TOLERANCE, (
        f'markers at {rate(markers):.3f} Hz, configured {marker_rate_hz} Hz')
    diagnostics_hz = rate(diagnostics_stamps)
    assert abs(diagnostics_hz * diagnostics_period_s - 1.0) < TOLERANCE, (
        f'diagnostics at {diagnostics_hz:.3f} Hz, configured every {diagnostics_period_s} s')
    assert not node.observer.pending
