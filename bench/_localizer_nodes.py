"""
The node half of ``bench_localizer.py``: ``landmark_localizer`` next to a relay node.

See ``bench_localizer.py``'s docstring. ``relay_main`` is the relay process (run as
``bench_localizer.py --relay``); ``node_costs`` the driver.
"""

import os
from pathlib import Path
import statistics
import sys
import tempfile
import time

import _common
import numpy as np

MS = 1_000_000
WINDOW = 8
KINDS = ('relay', 'localizer')
NAMESPACES = {'relay': '/bench_relay', 'localizer': '/bench_localizer'}


def relay_main():
    """Run the relay: odometry -> pose, observations -> observations_relayed."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from landmark_ros.ros import qos
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2

    class Relay(Node):
        """Receive and republish, nothing else."""

        def __init__(self):
            super().__init__('bench_relay')
            depth = qos.reliable_output(1000)
            self.pose = self.create_publisher(PoseWithCovarianceStamped, 'pose', depth)
            self.clouds = self.create_publisher(PointCloud2, 'observations_relayed', depth)
            self.out = PoseWithCovarianceStamped()
            self.create_subscription(Odometry, 'odometry', self.on_odometry, depth)
            self.create_subscription(PointCloud2, 'observations', self.clouds.publish, depth)

        def on_odometry(self, msg):
            self.out.header = msg.header
            self.out.pose.pose = msg.pose.pose
            self.pose.publish(self.out)

    rclpy.init()
    node = Relay()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def _start(launcher, work, landmarks):
    from landmark_ros.fuser import map_file
    from landmark_ros.ros.launcher import write_params_file
    records = [{'id': i, 'mean': [float(v) for v in m], 'observations': 0,
                'covariance': [[1e-3, 0.0], [0.0, 1e-3]]} for i, m in enumerate(landmarks)]
    map_file.save(str(work / 'map.json'), records, 'map', 'bench')
    write_params_file(work / 'localizer.yaml', {'/bench_localizer/landmark_localizer': {
        'map_file': str(work / 'map.json'), 'input_depth': 1000,
        'initial_stddev': [0.01, 0.01, 0.01]}})
    ns = NAMESPACES['localizer']
    args = ['-r', f'__ns:={ns}', '--params-file', str(work / 'localizer.yaml')]
    for topic in ('odometry', 'observations'):
        args += ['-p', f'qos_overrides.{ns}/{topic}.subscription.reliability:=reliable']
    launcher.start_module('localizer', 'landmark_ros.nodes.localizer', args)
    launcher.start('relay', [sys.executable, str(Path(__file__).with_name(
        'bench_localizer.py')), '--relay', '--ros-args', '-r', '__ns:=/bench_relay'])


class _Driver:
    """Publishers and pose subscriptions of both nodes in one executor."""

    def __init__(self, node, executor, rows, landmarks):
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from landmark_ros.ros import qos
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import PointCloud2
        self.node, self.executor, self.rows, self.landmarks = node, executor, rows, landmarks
        depth = qos.reliable_output(1000)
        self.pubs, self.poses = {}, {k: 0 for k in KINDS}
        for kind in KINDS:
            ns = NAMESPACES[kind]
            self.pubs[kind] = (node.create_publisher(Odometry, f'{ns}/odometry', depth),
                               node.create_publisher(PointCloud2, f'{ns}/observations', depth))
            node.create_subscription(PoseWithCovarianceStamped, f'{ns}/pose',
                                     lambda _m, k=kind: self._count(k), depth)
        self.stamp = {k: 0 for k in KINDS}
        self.odom = Odometry()
        self.odom.header.frame_id, self.odom.child_frame_id = 'odom', 'base_link'

    def _count(self, kind):
        self.poses[kind] += 1

    def connect(self, timeout_s=120.0):
        deadline = time.monotonic() + timeout_s
        while not all(p.get_subscription_count() and self.node.count_publishers(
                f'{NAMESPACES[k]}/pose') for k in KINDS for p in self.pubs[k]):
            if time.monotonic() > deadline:
                raise RuntimeError('the nodes did not connect')
            self.executor.spin_once(timeout_sec=0.05)

    def run(self, kind, count):
        """Send ``count`` odometry messages (and sightings); return wall seconds."""
        from landmark_ros.core import sensors
        from landmark_ros.localizer import motion
        from landmark_ros.ros.schemas import observation_message
        from std_msgs.msg import Header
        odom_pub, obs_pub = self.pubs[kind]
        start, sent, t0 = self.poses[kind], 0, time.monotonic()
        twist = np.array([0.3, 0.1])
        while self.poses[kind] - start < count:
            if sent < count and sent - (self.poses[kind] - start) < WINDOW:
                k = self.stamp[kind]
                self.stamp[kind] += 1
                stamp = k * 20 * MS
                self.odom.header.stamp.sec, self.odom.header.stamp.nanosec = divmod(
                    stamp, 1_000_000_000)
                self.odom.twist.twist.linear.x, self.odom.twist.twist.angular.z = twist
                odom_pub.publish(self.odom)
                sent += 1
                if k % 5 == 0:
                    x = motion.compose(np.zeros(3), motion.delta_from_twist(
                        twist[0], twist[1], k * 0.02))
                    ids = np.arange(self.rows) % len(self.landmarks)
                    z = sensors.observe(np.tile(x, (self.rows, 1)), self.landmarks[ids])
                    header = Header(frame_id='base_link')
                    header.stamp = self.odom.header.stamp
                    obs_pub.publish(observation_message(header, ids, z))
                continue
            self.executor.spin_once(timeout_sec=1.0)
            if time.monotonic() - t0 > 300:
                raise RuntimeError(f'{kind}: stalled')
        return time.monotonic() - t0


def node_costs(rounds, messages, rows):
    """Return per kind the median msg/s and CPU us per odometry message, and the ratios."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from landmark_ros.ros.launcher import Launcher
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    domain = 150 + os.getpid() % 30
    rng = np.random.default_rng(0)
    landmarks = rng.uniform(-10, 10, (20, 2))
    work = Path(tempfile.mkdtemp(prefix='bench_localizer_'))
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    node = executor = None
    runs = {k: [] for k in KINDS}
    with Launcher(work, domain_id=domain) as launcher:
        try:
            _start(launcher, work, landmarks)
            node = rclpy.create_node('bench_localizer_driver', context=context)
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(node)
            driver = _Driver(node, executor, rows, landmarks)
            driver.connect()
            for kind in KINDS:  # warm-up
                driver.run(kind, 100)
            for _ in range(rounds):
                for kind in KINDS:
                    pid = launcher.processes[kind].pid
                    cpu0 = _common.process_cpu_s(pid)
                    wall = driver.run(kind, messages)
                    cpu = _common.process_cpu_s(pid) - cpu0
                    runs[kind].append((messages / wall, cpu / messages))
                    launcher.check()
        finally:
            if executor is not None:
                executor.shutdown()
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown(context=context)
    out = {}
    for kind in KINDS:
        out[f'{kind}_msg_per_s'] = statistics.median(r for r, _ in runs[kind])
        out[f'{kind}_cpu_us_per_msg'] = statistics.median(c for _, c in runs[kind]) * 1e6
    out['ratio'] = out['localizer_msg_per_s'] / out['relay_msg_per_s']
    out['cpu_ratio'] = out['relay_cpu_us_per_msg'] / out['localizer_cpu_us_per_msg']
    return out


def mrclam_real_time():
    """Return the offline MRCLAM localization's real-time factors, or None without data."""
    from landmark_ros.mrclam.config import default_dataset_path, load_config
    from landmark_ros.mrclam.data import load_dataset
    from landmark_ros.mrclam.localize import localizer_config, run, surveyed_map
    from landmark_ros.mrclam.localize_cli import _sections
    from landmark_ros.mrclam.localize_data import load_all_extras
    path = Path(__file__).resolve().parents[1].parent / 'shared' / 'data' / 'mrclam' / 'dataset6'
    for candidate in (path, Path('/work/shared/data/mrclam/dataset6'), default_dataset_path()):
        if candidate.is_dir():
            path = candidate
            break
    else:
        return None
    config = load_config(None)
    dataset = load_dataset(path, config.pose_stddev)
    localizer_values, replay_values = _sections(config.path)
    extras = load_all_extras(dataset)
    t0, cpu0 = time.monotonic(), time.process_time()
    run(dataset, extras, localizer_config(localizer_values), surveyed_map(dataset), False,
        float(replay_values.get('odometry_delay_s', 0.0)))
    wall, cpu = time.monotonic() - t0, time.process_time() - cpu0
    return {'mrclam_real_time_cpu': dataset.duration / cpu,
            'mrclam_real_time_wall': dataset.duration / wall}
