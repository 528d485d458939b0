"""The nodes with ros.fast_io on, off, and without one of the rclpy internals it uses."""

import numpy as np
import pytest
import rclpy.waitable
from rigs import FuserRig, ObserverRig

C_UNIT = 0.01 * np.eye(2)
P1 = np.array([1.0, 2.0, 0.5])
Z = np.array([4.0, 0.7])


def _fuse_two_sources(env, rig):
    """Send one landmark from each of two sources; return the fused map's IDs."""
    rig.send('a/landmarks', [1], [[1.0, 1.0]], [C_UNIT])
    rig.send('b/landmarks', [1, 2], [[1.0, 1.2], [5.0, 5.0]], [C_UNIT, C_UNIT])
    return sorted(rig.wait_map(lambda rows: len(rows[0]) == 2)[0].tolist())


def test_without_an_internal_the_fuser_uses_plain_rclpy_and_still_fuses(
        env, monkeypatch, capfd):
    monkeypatch.delattr(rclpy.waitable, 'NumberOfEntities')    # what BurstGroup uses
    rig = FuserRig(env, min_observations=1)
    inputs = rig.node.landmark_inputs
    assert not inputs.fast and inputs._group is None and not inputs._raw
    assert _fuse_two_sources(env, rig) == [1, 2]
    assert rig.node.sources['b/landmarks'].counts['messages_in'] == 1
    log = capfd.readouterr().err
    assert log.count('fast_io: this rclpy has no rclpy.waitable.NumberOfEntities') == 1, log


@pytest.mark.parametrize('fast', [True, False])
def test_the_switch_chooses_the_path_and_the_map_is_the_same(env, fast):
    rig = FuserRig(env, min_observations=1, fast_io=fast)
    inputs = rig.node.landmark_inputs
    assert inputs.fast == fast and (inputs._group is not None) == fast
    assert _fuse_two_sources(env, rig) == [1, 2]
    ids, m, P, _, observations = rig.node.fuser.map.snapshot()
    assert observations.tolist() == [2, 1]
    np.testing.assert_allclose(m[0], [1.0, 1.1], atol=1e-12)


@pytest.mark.parametrize('fast', [True, False])
def test_the_observer_places_a_landmark_either_way(env, fast):
    rig = ObserverRig(env, fast_io=fast)
    assert rig.node.observation_inputs.fast == fast
    assert len(rig.node._periodic.timers) == (1 if fast else 3)
    m = rig.observe_one(10.0, P1, np.zeros((3, 3)), Z)[1]
    bearing = P1[2] + Z[1]
    np.testing.assert_allclose(m[0], P1[:2] + Z[0] * np.array([np.cos(bearing),
                                                               np.sin(bearing)]), atol=1e-9)
