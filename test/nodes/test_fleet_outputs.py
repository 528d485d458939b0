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
                          and rig.node.outputs.marker_pub.get_subscription_count(), DEADLINE_S)
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


def test_a_merged_track_is_announced_on_the_updates_and_its_markers_deleted(env):
    from landmark_ros.pipeline.rows import UNKNOWN_ID
    from landmark_ros.ros.schemas import read_removed
    rig = FuserRig(env, min_observations=1, updates_rate_hz=50.0)
    updates = Collector(rig.tester, PointCloud2, f'{rig.ns}/fused_landmark_updates', RELIABLE)
    markers = Collector(rig.tester, MarkerArray, f'{rig.ns}/fused_markers', LATCHED)
    assert env.spin_until(lambda: updates.subscription.get_publisher_count()
                          and rig.node.outputs.marker_pub.get_subscription_count(), DEADLINE_S)
    # Two tracks found without IDs, 5 cm apart, never in one message (set up in the
    # node's own pipeline objects, as association over several messages leaves them).
    fuser = rig.node.fuser
    a, b = fuser.tracker.allocate(fuser.map), fuser.tracker.allocate(fuser.map)
    P = np.broadcast_to(0.01 * np.eye(2), (3, 2, 2)).copy()
    fuser.map.update([a, a, a], np.zeros((3, 2)), P, 0 * P, 'x', 1)
    fuser.map.update([b, b], np.array([[0.05, 0.0]] * 2), P[:2], 0 * P[:2], 'x', 1)
    fuser.map_changed = True
    assert env.spin_until(lambda: markers.messages
                          and marker_ids(markers.messages[-1]) == sorted(
                              [a - (1 << 32), b - (1 << 32)] if a >= 1 << 31 else [a, b]),
                          DEADLINE_S)
    seen_updates, seen_markers = len(updates.messages), len(markers.messages)
    # A row without an ID next to b: b changes, the merge check folds b into a.
    rig.send('a/landmarks', [UNKNOWN_ID], [[0.05, 0.0]], [C])
    assert env.spin_until(lambda: any(len(read_removed(msg)[0]) for msg in
                                      updates.messages[seen_updates:]), DEADLINE_S)
    message = next(msg for msg in updates.messages[seen_updates:] if len(read_removed(msg)[0]))
    removed, into = read_removed(message)
    assert removed.tolist() == [b] and into.tolist() == [a]
    rows = decode(message)
    kept = rows.ids.tolist().index(a)
    gone = rows.ids.tolist().index(b)
    assert rows.observations[gone] == 0 and rows.observations[kept] >= 5
    np.testing.assert_array_equal(rows.m[gone], rows.m[kept])
    assert np.isfinite(rows.P).all()
    ok = env.spin_until(lambda: any(
        m.action == Marker.DELETE and m.ns == 'ellipses' for array in
        markers.messages[seen_markers:] for m in array.markers), DEADLINE_S)
    assert ok, [[(m.ns, m.id, m.action) for m in array.markers] for array in markers.messages]
    assert rig.wait_map(lambda rows: rows.ids.tolist() == [a]).observations.tolist()[0] >= 5
    # Plain updates keep the plain schema (no merged_into field).
    seen_updates = len(updates.messages)
    rig.send('a/landmarks', [UNKNOWN_ID], [[0.0, 0.01]], [C])
    assert env.spin_until(lambda: len(updates.messages) > seen_updates, DEADLINE_S)
    assert 'merged_into' not in [f.name for f in updates.messages[-1].fields]
