"""The fuser's fleet-size outputs over DDS: updates of changed landmarks, markers, shards."""

from landmark_ros.ros.qos import LATCHED
import numpy as np
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rigs import DEADLINE_S, decode, FuserRig
from rosutil import Collector
from sensor_msgs.msg import PointCloud2
from test_fuser_node import C
from visualization_msgs.msg import Marker, MarkerArray

RELIABLE = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)


def marker_ids(array):
    """Return the IDs of the ellipse markers of a MarkerArray."""
    return sorted(m.id for m in array.markers if m.ns == 'ellipses' and m.action == Marker.ADD)


def test_updates_carry_only_the_changed_landmarks_and_markers_follow(env):
    rig = FuserRig(env, min_observations=1, updates_rate_hz=50.0)
    updates = Collector(rig.tester, PointCloud2, f'{rig.ns}/fused_landmark_updates', RELIABLE)
    markers = Collector(rig.tester, MarkerArray, f'{rig.ns}/fused_markers', LATCHED)
    assert env.spin_until(lambda: updates.subscription.get_publisher_count()
                          and rig.node.marker_pub.get_subscription_count(), DEADLINE_S)
    ids = list(range(10))
    rig.send('a/landmarks', ids, np.column_stack([ids, ids]), [C] * 10)
    assert env.spin_until(lambda: updates.messages and markers.messages, DEADLINE_S)
    assert decode(updates.messages[-1]).ids.tolist() == ids
    assert env.spin_until(lambda: marker_ids(markers.messages[-1]) == ids, DEADLINE_S)

    seen_updates, seen_markers = len(updates.messages), len(markers.messages)
    rig.send('a/landmarks', [3, 7], [[3.0, 3.0], [7.0, 7.0]], [C, C])
    assert env.spin_until(lambda: len(updates.messages) > seen_updates
                          and len(markers.messages) > seen_markers, DEADLINE_S)
    rows = decode(updates.messages[-1])
    assert rows.ids.tolist() == [3, 7] and rows.observations.tolist() == [2, 2]
    assert marker_ids(markers.messages[-1]) == [3, 7]           # ADD replaces by ID
    full = rig.wait_map(lambda rows: rows.observations.tolist()[3] == 2)
    assert full.ids.tolist() == ids

    # A late marker subscriber gets every landmark again, not the last update only.
    late = Collector(rig.tester, MarkerArray, f'{rig.ns}/fused_markers', LATCHED)
    assert env.spin_until(lambda: late.messages and marker_ids(late.messages[-1]) == ids,
                          DEADLINE_S)


def test_two_shard_nodes_split_the_landmarks_by_id(ros_env):
    shards = [FuserRig(ros_env(), min_observations=1, shard_count=2, shard_index=k)
              for k in range(2)]
    ids = list(range(6))
    for rig in shards:
        rig.send('a/landmarks', ids, np.column_stack([ids, ids]), [C] * 6)
    maps = [rig.wait_map(lambda rows: len(rows.ids) == 3).ids.tolist() for rig in shards]
    assert maps == [[0, 2, 4], [1, 3, 5]]
    assert shards[0].counts('a/landmarks')['other_shard'] == 3
