"""Tests of ros.qos.incompatible_policy: which publisher QoS cannot serve a subscription."""

from landmark_ros.ros import qos
import pytest
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

INFINITE_NS = 0x7fffffffffffffff     # what get_publishers_info_by_topic reports


def profile(reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE,
            deadline_ns=0):
    """Return a QoS profile with the given policies (deadline 0: the default, none)."""
    return QoSProfile(depth=10, reliability=reliability, durability=durability,
                      deadline=Duration(nanoseconds=deadline_ns))


@pytest.mark.parametrize('requested, offered, expected', [
    (profile(), profile(), None),
    (profile(), profile(deadline_ns=INFINITE_NS), None),
    (profile(), profile(ReliabilityPolicy.BEST_EFFORT), 'RELIABILITY'),
    (profile(ReliabilityPolicy.BEST_EFFORT), profile(), None),
    (profile(ReliabilityPolicy.BEST_EFFORT), profile(ReliabilityPolicy.BEST_EFFORT), None),
    (profile(durability=DurabilityPolicy.TRANSIENT_LOCAL), profile(), 'DURABILITY'),
    (profile(), profile(durability=DurabilityPolicy.TRANSIENT_LOCAL), None),
    (profile(deadline_ns=10 ** 8), profile(deadline_ns=2 * 10 ** 8), 'DEADLINE'),
    (profile(deadline_ns=10 ** 8), profile(deadline_ns=INFINITE_NS), 'DEADLINE'),
    (profile(deadline_ns=10 ** 8), profile(deadline_ns=10 ** 7), None),
    (profile(deadline_ns=INFINITE_NS), profile(deadline_ns=10 ** 9), None),
])
def test_a_publisher_must_offer_at_least_what_the_subscription_requests(
        requested, offered, expected):
    assert qos.incompatible_policy(requested, offered) == expected


def test_the_simulator_streams_serve_default_and_replayed_inputs():
    from landmark_ros.nodes.sim import STREAM_QOS
    assert STREAM_QOS.durability == DurabilityPolicy.TRANSIENT_LOCAL
    replayed = qos.sensor_input(10)
    replayed.reliability = ReliabilityPolicy.RELIABLE
    replayed.durability = DurabilityPolicy.TRANSIENT_LOCAL
    for requested in (qos.sensor_input(10), qos.reliable_input(10), replayed):
        assert qos.incompatible_policy(requested, STREAM_QOS) is None
    # A replayed input cannot take a volatile publisher (the localizers' pose).
    assert qos.incompatible_policy(replayed, qos.reliable_output(10)) == 'DURABILITY'


def test_replayed_input_overrides_name_each_topic_of_the_namespace():
    overrides = qos.replayed_input_overrides('/robot2', ('observations', 'pose'))
    assert overrides == {
        'qos_overrides./robot2/observations.subscription.reliability': 'reliable',
        'qos_overrides./robot2/observations.subscription.durability': 'transient_local',
        'qos_overrides./robot2/pose.subscription.reliability': 'reliable',
        'qos_overrides./robot2/pose.subscription.durability': 'transient_local'}
    arguments = qos.replayed_input_arguments('/robot2', ('pose',))
    assert arguments == ['-p', 'qos_overrides./robot2/pose.subscription.reliability:=reliable',
                         '-p', 'qos_overrides./robot2/pose.subscription.durability:='
                         'transient_local']
