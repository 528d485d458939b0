"""``partial_observations`` clouds: the range scale columns travel, and old clouds still read."""

from landmark_ros.core.partial import RANGE, Views
from landmark_ros.pipeline.partial_rows import (NO_RANGE_SCALE_ROW, PARTIAL_COLUMNS,
                                                PartialObservations, RANGE_SCALE_COLUMNS)
from landmark_ros.ros.cloud import CloudWriter
from landmark_ros.ros.schemas import (make_header, partial_observation_message, PARTIAL_SCHEMA,
                                      read_partial_observations)
import numpy as np


def observations():
    views = Views(RANGE, [[0.5, 1.0, 0.2], [2.0, -1.0, 3.0]], np.eye(3) * 1e-4, [2.5, 3.5],
                  1e-3, 2e-3, [[0.04, -0.005, -0.46], [0.01, 0.0, -0.3]], [0.59, 0.6])
    return PartialObservations(np.array([4, 9]), views, np.array([7, 8]))


def test_the_range_scale_columns_round_trip():
    columns = observations().columns()
    read = read_partial_observations(partial_observation_message(make_header(2.0, 'map'),
                                                                 columns))
    assert set(read) == set(PARTIAL_COLUMNS + RANGE_SCALE_COLUMNS)
    for name in RANGE_SCALE_COLUMNS:
        np.testing.assert_array_equal(read[name], columns[name])


def test_a_cloud_without_them_reads_with_none():
    old = tuple((name, dtype) for name, dtype in PARTIAL_SCHEMA if name in PARTIAL_COLUMNS)
    writer = CloudWriter(old)
    rows = writer.rows(2)
    for name in PARTIAL_COLUMNS:
        rows[name] = observations().columns()[name]
    read = read_partial_observations(writer.message(make_header(2.0, 'map'), rows))
    assert not set(RANGE_SCALE_COLUMNS) & set(read)
    # Written without them, a cloud carries no range scale.
    columns = {name: observations().columns()[name] for name in PARTIAL_COLUMNS}
    again = read_partial_observations(partial_observation_message(make_header(2.0, 'map'),
                                                                  columns))
    for name, value in zip(RANGE_SCALE_COLUMNS, NO_RANGE_SCALE_ROW):
        np.testing.assert_array_equal(again[name], [value, value])
