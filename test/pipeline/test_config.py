"""Tests of pipeline.config: the parameter dataclasses validate themselves."""

import dataclasses
import math

from landmark_ros.pipeline import config
import pytest


# --- config --------------------------------------------------------------------------------------

@pytest.mark.parametrize('cls', [config.ObserverConfig, config.FuserConfig])
def test_config_defaults_are_valid(cls):
    cfg = cls()
    for spec in dataclasses.fields(cls):
        value = getattr(cfg, spec.name)
        assert value == config.field_default(spec)
        low, high = spec.metadata['low'], spec.metadata['high']
        if low is not None:
            assert low <= value <= high
        assert spec.metadata['description']
    assert cls.from_values({}) == cfg
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.log_throttle_s = 1.0


def test_config_coercion_of_numbers():
    cfg = config.ObserverConfig(range_stddev=1, max_pending=5.0, sensor_pose=[1, 2, 0.5])
    assert cfg.range_stddev == 1.0 and type(cfg.range_stddev) is float
    assert cfg.max_pending == 5 and type(cfg.max_pending) is int
    assert cfg.sensor_pose == (1.0, 2.0, 0.5)
    assert all(type(v) is float for v in cfg.sensor_pose)
    cfg = config.FuserConfig(input_topics=['a', 'b'])
    assert cfg.input_topics == ('a', 'b')


@pytest.mark.parametrize('cls, name, value, message', [
    (config.ObserverConfig, 'range_stddev', True, 'must be a number'),
    (config.ObserverConfig, 'range_stddev', '0.1', 'must be a number'),
    (config.ObserverConfig, 'range_stddev', None, 'must be a number'),
    (config.ObserverConfig, 'range_stddev', math.nan, 'must be finite'),
    (config.ObserverConfig, 'max_wait_s', math.inf, 'must be finite'),
    (config.ObserverConfig, 'max_pending', 5.5, 'must be an integer'),
    (config.ObserverConfig, 'max_pending', False, 'must be a number'),
    (config.ObserverConfig, 'world_frame', 5, 'must be a string'),
    (config.ObserverConfig, 'sensor_pose', (0.0, 0.0), 'must have 3 entries'),
    (config.ObserverConfig, 'sensor_pose', (0.0, 0.0, 0.0, 0.0), 'must have 3 entries'),
    (config.ObserverConfig, 'sensor_pose', (0.0, 'x', 0.0), 'must hold finite numbers'),
    (config.ObserverConfig, 'sensor_pose', (0.0, True, 0.0), 'must hold finite numbers'),
    (config.ObserverConfig, 'sensor_pose', (0.0, math.nan, 0.0), 'must hold finite numbers'),
    (config.FuserConfig, 'input_topics', ['a', 3], 'must be a list of strings'),
    (config.FuserConfig, 'gate_probability', 1, 'outside'),
    (config.FuserConfig, 'gate_probability', 0.4, 'outside'),
    (config.FuserConfig, 'min_observations', 0, 'outside'),
    (config.ObserverConfig, 'range_stddev', -0.1, 'outside'),
    (config.ObserverConfig, 'bearing_stddev', 3.2, 'outside'),
    (config.ObserverConfig, 'pose_buffer_s', 0.0, 'outside'),
])
def test_config_rejects_bad_values(cls, name, value, message):
    with pytest.raises(ValueError, match=message):
        cls(**{name: value})
    with pytest.raises(ValueError, match=message):
        cls.from_values({name: value})


def test_config_range_limits_are_inclusive():
    assert config.ObserverConfig(bearing_stddev=math.pi).bearing_stddev == math.pi
    assert config.ObserverConfig(range_stddev=0.0).range_stddev == 0.0
    assert config.FuserConfig(gate_probability=0.999999).gate_probability == 0.999999


def test_config_relations():
    with pytest.raises(ValueError, match='max_pose_gap_s'):
        config.ObserverConfig(pose_buffer_s=1.0, max_pose_gap_s=2.0)
    assert config.ObserverConfig(pose_buffer_s=2.0, max_pose_gap_s=2.0).max_pose_gap_s == 2.0
    with pytest.raises(ValueError, match='fusion'):
        config.FuserConfig(fusion='average')
    for fusion in ('independent', 'covariance_intersection', 'split_covariance_intersection'):
        assert config.FuserConfig(fusion=fusion).fusion == fusion
    with pytest.raises(ValueError, match='at least one topic'):
        config.FuserConfig(input_topics=[])
    with pytest.raises(ValueError, match='at least one topic'):
        config.FuserConfig(input_topics=['a', ''])
    with pytest.raises(ValueError, match='repeat'):
        config.FuserConfig(input_topics=['a', 'b', 'a'])


def test_config_from_values_ignores_unknown_names():
    cfg = config.FuserConfig.from_values({'fusion': 'independent', 'use_sim_time': True,
                                          'qos_overrides': {}})
    assert cfg.fusion == 'independent'


def test_config_rejects_a_string_for_a_list_of_strings():
    with pytest.raises(ValueError):
        config.FuserConfig(input_topics='ab')
