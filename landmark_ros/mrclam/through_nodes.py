"""
The replay through the real nodes, over DDS (``--through-nodes``).

``run_through_nodes`` starts one ``landmark_observer`` per robot and one
``landmark_fuser`` per fusion method as processes (``landmark_ros.ros.launcher``) in
a private ROS domain on the loopback interface, with ``--params-file`` the replay's
config plus the transport overrides ``OBSERVER_TRANSPORT`` and ``FUSER_TRANSPORT``;
``player.Player`` publishes the dataset into them, then each fuser's saved map and
diagnostics are read back. What to start and in which order, without ROS, is
``replay_plan``'s. ``landmark_ros.mrclam.cli`` imports this module only for
``--through-nodes``.
"""

from dataclasses import dataclass
import os
from pathlib import Path
import shutil
import tempfile
import time
from typing import Optional, Tuple

from landmark_ros.fuser import map_file
from landmark_ros.mrclam.player import Player
from landmark_ros.mrclam.replay_plan import (cpu_seconds, domain_id_for, fuser_arguments,
                                             FUSER_TRANSPORT, hidden_association,
                                             observer_arguments, OBSERVER_TRANSPORT,
                                             partial_topic, PlayOptions, ReplayError)
from landmark_ros.mrclam.report import method_result
from landmark_ros.ros.launcher import Launcher, ProcessExitedError
from landmark_ros.ros.schemas import read_landmarks
import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor


@dataclass(frozen=True)
class ReplaySetup:
    """What one replay through the nodes plays, where it works, and into which topics."""

    dataset: object
    rows: object
    config: object
    methods: Tuple[str, ...]
    options: PlayOptions
    work: Path
    config_path: Path
    topics: Tuple[str, ...]
    partial_observation_topics: Optional[Tuple[str, ...]]

    def map_path(self, method):
        """Return where a method's fuser saves its map."""
        return self.work / f'{method}.json'


def start_nodes(setup, launcher):
    """Start one observer per robot and one fuser per method."""
    for robot in setup.dataset.robots:
        launcher.start_module(f'observer_{robot.name}', 'landmark_ros.nodes.observer',
                              observer_arguments(robot, setup.config_path))
    for method in setup.methods:
        launcher.start_module(f'fuser_{method}', 'landmark_ros.nodes.fuser',
                              fuser_arguments(method, setup.topics, setup.config_path,
                                              setup.map_path(method),
                                              setup.partial_observation_topics))


def collect_method(setup, player, final, method):
    """
    Return a method's ``MethodResult`` from its saved map, and what disagrees (or None).

    The fuser's ``fused_landmarks`` must equal its saved map; with partial observation topics, the
    fuser's ``partial_in`` must equal the partial observation rows the player received.
    """
    dataset = setup.dataset
    document = map_file.load(setup.map_path(method), setup.config.fuser.world_frame)
    records = sorted(document['landmarks'], key=lambda r: r['id'])
    mismatch = None

    def cloud_matches():
        msg = player.fused.get(method)
        if msg is None:
            return False
        cloud = read_landmarks(msg)
        return (cloud.ids.tolist() == [r['id'] for r in records]
                and np.array_equal(cloud.m, np.array(
                    [r['mean'] for r in records]).reshape(-1, 2))
                and np.array_equal(cloud.P, np.array(
                    [r['covariance'] for r in records]).reshape(-1, 2, 2))
                and cloud.observations.tolist() == [r['observations'] for r in records])
    try:
        player.spin_until(cloud_matches, 10.0, f'{method} fused_landmarks')
    except ReplayError:
        mismatch = 'fused_landmarks never matched the saved map'
    sources = final[method]['sources']
    used = sum(int(v.get('fused', 0)) + int(v.get('partial_fused', 0))
               for v in sources.values())
    rejected = sum(int(v.get('gated_out', 0)) + int(v.get('partial_gated', 0))
                   for v in sources.values())
    association = (hidden_association(records, dataset.landmarks)
                   if setup.options.hide_ids else None)
    result = method_result(method, records, dataset.landmarks, used, rejected)
    result.association = association
    result.sensor = setup.options.sensor
    result.landmarks_initialised = sum(
        int(v.get('landmarks_initialised', 0)) for v in sources.values())
    if setup.partial_observation_topics:
        taken = sum(int(sources[t].get('partial_in', 0)) for t in setup.partial_observation_topics)
        if taken != player.partial_rows_out:
            mismatch = (f'partial_in {taken}, partial observation rows published '
                        f'{player.partial_rows_out}')
    return result, mismatch


def node_info(setup, player, final, cpu, times):
    """Return the replay's timing, message counts, CPU time and node diagnostics."""
    t_start, t_connect = times
    observers = {r.name: player.diagnostics[f'/{r.name}/landmark_observer'][1]
                 for r in setup.dataset.robots}
    return {
        'wall_s': time.monotonic() - t_start,
        'startup_s': t_connect - t_start,
        'play_wall_s': player.play_wall_s,
        'speedup': (setup.dataset.duration / player.play_wall_s if player.play_wall_s
                    else None),
        'clouds': int(len(player.starts)), 'rows': int(len(player.rows)),
        'rows_out': int(player.rows_out),
        'partial_rows_out': int(player.partial_rows_out),
        'barriers': player.barriers, 'barrier_rounds': player.barrier_rounds,
        'probes': list(player.probes_sent),
        'fusers': {m: final[m]['sources'] for m in setup.methods},
        'observers': observers, 'cloud_mismatch': {},
        'cpu_s': {name: round(value, 2) for name, value in cpu.items()},
    }


def replay(setup, launcher, context, domain, t_start):
    """Start the nodes, play the dataset and collect the results (``run_through_nodes``)."""
    node = executor = None
    try:
        start_nodes(setup, launcher)
        rclpy.init(args=['landmark_mrclam'], context=context, domain_id=domain)
        node = rclpy.create_node('landmark_mrclam_player', context=context,
                                 start_parameter_services=False)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        player = Player(node, executor, setup.dataset, setup.rows, setup.config,
                        setup.methods, launcher, setup.options)
        t_connect = time.monotonic()
        cpu_player = time.process_time()
        try:
            final = player.run()
        except ProcessExitedError as error:
            raise ReplayError(str(error)) from error
        cpu = cpu_seconds({name: p.pid for name, p in launcher.processes.items()})
        cpu['player'] = time.process_time() - cpu_player
        results, mismatch = {}, {}
        for method in setup.methods:
            results[method], problem = collect_method(setup, player, final, method)
            if problem is not None:
                mismatch[method] = problem
        info = node_info(setup, player, final, cpu, (t_start, t_connect))
        info['cloud_mismatch'] = mismatch
        return results, info
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()


def run_through_nodes(dataset, config, methods, options=PlayOptions(), keep_logs=False,
                      out=print, domain_id=None):
    """
    Replay the dataset through the real nodes; return the results per method.

    The nodes run as processes of ``landmark_ros.ros.launcher.Launcher`` (stopped with
    SIGINT, then SIGTERM and SIGKILL, whatever happens) in a private ROS domain on the
    loopback interface; this process joins it with its own context. ``options``
    (``PlayOptions``): ``progress`` chooses the progress bar as in ``progress_bar``
    (None: only on a terminal); ``hide_ids`` sends every row as ``UNKNOWN_ID``
    (``Player``); each result then has its ``association`` (``hidden_association``) and
    its records take the IDs of the true landmarks matched (``track_id`` keeps the
    fuser's). ``sensor`` ``range`` or ``bearing`` drops a column of every cloud
    (``Player``) and gives each fuser the ``partial_observation_topics``
    ``/robotN/partial_observations``; the fusers' ``partial_in`` must then equal the
    partial observation rows the player received (else ``cloud_mismatch``).

    Returns
    -------
    results : dict
        Method -> MethodResult: each fuser's saved map (``~/save``), with the
        per-landmark rejections; its ``fused_landmarks`` must equal it.
    info : dict
        Timing, message counts, CPU time per process and the node diagnostics.

    """
    t_start = time.monotonic()
    domain = domain_id_for() if domain_id is None else int(domain_id)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    work = Path(tempfile.mkdtemp(prefix='landmark_mrclam_'))
    topics = tuple(robot.landmarks_topic for robot in dataset.robots)
    setup = ReplaySetup(
        dataset=dataset, rows=dataset.rows(), config=config, methods=tuple(methods),
        options=options, work=work, config_path=Path(config.path).resolve(), topics=topics,
        partial_observation_topics=(None if options.sensor == 'rb'
                                    else tuple(partial_topic(t) for t in topics)))
    context = Context()
    ok = False
    out(f'through the nodes: ROS_DOMAIN_ID={domain}, loopback only; logs in {work}')
    out(f'  observers {", ".join(r.name for r in dataset.robots)}: --params-file '
        f'{setup.config_path} + {OBSERVER_TRANSPORT} + reliable pose/observations')
    out(f'  fusers /mrclam/<method>: --params-file {setup.config_path} + {FUSER_TRANSPORT}')
    launcher = Launcher(work, domain_id=domain)
    try:
        results, info = replay(setup, launcher, context, domain, t_start)
        ok = True
        return results, info
    finally:
        rclpy.try_shutdown(context=context)
        codes = launcher.stop()
        bad = {name: code for name, code in codes.items() if code != 0}
        if bad:
            out(f'processes exited with {bad}')
        if ok and not keep_logs and not bad:
            shutil.rmtree(work, ignore_errors=True)
        else:
            out(f'logs kept in {work}')
