"""
Benchmark: what the fuser publishes for a fleet, before and after incremental outputs.

A 10,000-landmark map (split CI, 5 sources) is updated by 5 robots sending 10
messages/s of 100 rows each. Per second of that traffic the fuser publishes:

before
    the full map (``fused_landmarks``) and the full markers at ``publish_rate_hz``
    (5 Hz), as the fuser did before ``fused_landmark_updates`` existed;
after
    ``fused_landmark_updates`` and the markers of the changed landmarks only at
    ``updates_rate_hz`` (10 Hz), and the full map at a fleet-sized
    ``publish_rate_hz`` of 0.2 Hz.

Both sides build the real messages with the package's writers and serialise them
with ``rclpy.serialization`` (the bytes DDS would carry); the CPU time is the thread
CPU time of building and serialising, side by side in one run. The fusion itself is
the same on both sides and is left out (``bench_map.py`` times it).

Run from the repository root in the dev venv: ``python bench/bench_outputs.py``. The
last line is ``RESULT bench_outputs key=value ...``.
"""

import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import _common  # noqa: E402
from landmark_ros.fusion.landmark_map import LandmarkMap  # noqa: E402
from landmark_ros.ros.markers import landmark_markers  # noqa: E402
from landmark_ros.ros.schemas import fused_landmark_message  # noqa: E402
import numpy as np  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

LANDMARKS = 10_000
ROBOTS = 5
MESSAGES_PER_S = 10
ROWS = 100
SECONDS = 3


def make_map(rng):
    """Return a split-CI map of LANDMARKS landmarks seen by every robot, and the truth."""
    truth = rng.uniform(-500.0, 500.0, (LANDMARKS, 2))
    landmark_map = LandmarkMap('split_covariance_intersection')
    for robot in range(ROBOTS):
        ids = np.arange(LANDMARKS)
        z, R = observe(truth, ids, rng)
        landmark_map.update(ids, z, R, 0.3 * R, f'/robot{robot}/landmarks',
                            np.full(LANDMARKS, 10 ** 9, np.int64))
    return landmark_map, truth


def observe(truth, ids, rng):
    """Return noisy observations of ``ids`` and their covariance."""
    R = np.broadcast_to(np.diag([0.02, 0.03]), (len(ids), 2, 2)).copy()
    return truth[ids] + rng.normal(0.0, 0.1, (len(ids), 2)), R


def publish_cost(snapshot, markers):
    """Return (CPU seconds, bytes) of building and serialising a map cloud (+ markers)."""
    header = Header(frame_id='map')
    start = time.thread_time()
    ids, m, P, P_dep, observations = snapshot
    size = len(serialize_message(fused_landmark_message(header, ids, m, P, P_dep,
                                                        observations)))
    if markers:
        size += len(serialize_message(landmark_markers(header, ids, m, P, 2.0)))
    return time.thread_time() - start, size


def main():
    """Run the comparison and print the report."""
    print('bench_outputs: what the fuser publishes at 10,000 landmarks, before and after '
          'incremental outputs')
    print(_common.machine_line(_common.machine()))
    rng = np.random.default_rng(7)
    landmark_map, truth = make_map(rng)
    totals = {'before': [0.0, 0], 'after': [0.0, 0]}
    ticks = 0
    changed = []
    for tick in range(SECONDS * 10):              # 0.1 s steps of traffic
        ids = rng.integers(0, LANDMARKS, ROBOTS * MESSAGES_PER_S * ROWS // 10)
        z, R = observe(truth, ids, rng)
        result = landmark_map.update(ids, z, R, 0.3 * R, f'/robot{tick % ROBOTS}/landmarks',
                                     np.full(len(ids), 2 * 10 ** 9 + tick, np.int64))
        changed.append(result.changed_ids)
        ticks += 1
        # after: updates and changed markers at 10 Hz
        cpu, size = publish_cost(landmark_map.snapshot(np.unique(np.concatenate(changed))),
                                 markers=True)
        changed = []
        totals['after'][0] += cpu
        totals['after'][1] += size
        if tick % 50 == 0:                        # after: the full map at 0.2 Hz
            cpu, size = publish_cost(landmark_map.snapshot(), markers=False)
            totals['after'][0] += cpu
            totals['after'][1] += size
        if tick % 2 == 0:                         # before: full map and markers at 5 Hz
            cpu, size = publish_cost(landmark_map.snapshot(), markers=True)
            totals['before'][0] += cpu
            totals['before'][1] += size
    seconds = ticks / 10.0
    figures = {}
    for side, (cpu, size) in totals.items():
        figures[f'{side}_cpu_percent'] = 100.0 * cpu / seconds
        figures[f'{side}_mb_per_s'] = size / seconds / 1e6
        print(f'  {side:6s}: {100.0 * cpu / seconds:6.1f} % of a core, '
              f'{size / seconds / 1e6:7.2f} MB/s published')
    figures['cpu_ratio'] = figures['before_cpu_percent'] / figures['after_cpu_percent']
    figures['bytes_ratio'] = figures['before_mb_per_s'] / figures['after_mb_per_s']
    print(f"  after is {figures['cpu_ratio']:.1f}x less CPU and {figures['bytes_ratio']:.1f}x "
          'fewer bytes')
    print('RESULT bench_outputs ' + ' '.join(f'{k}={v:.4g}' for k, v in figures.items()))
    return figures


if __name__ == '__main__':
    main()
