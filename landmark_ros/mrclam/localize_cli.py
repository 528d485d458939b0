"""
The ``--localize`` and ``--calibrate-odometry`` modes of ``landmark_mrclam``.

``--localize``: ``mrclam.localize.run_all`` with the ``landmark_localizer`` section of the
params file (``config/mrclam.yaml``: the calibrated sensor and odometry models), the
odometry delay and the camera delay of its ``landmark_mrclam`` section (the sightings,
of landmarks and of robots, moved back by ``camera_delay_s``,
``localize_data.with_camera_delay``: the fused map is built from them too); prints the
per-robot table and which of the issue's targets hold; ``--json`` gains
``localization`` (one entry per map and mode), ``--plot FILE`` draws one picture per
run (``FILE`` stem + ``-MAP[-robots]``). Dead reckoning is the JSON's ``dead_reckoning``
entry (same keys), beside the ``localization`` list.

``--calibrate-odometry``: the odometry delay and alphas from the ground truth with the
leave-one-robot-out cross-check (``localize_data.calibrate_odometry``).
"""

from pathlib import Path
import sys

from landmark_ros.localizer.localizer import UNKNOWN_ID
from landmark_ros.mrclam.config import node_section
from landmark_ros.mrclam.localize import (format_table, fused_map, localizer_config,
                                          run_all, surveyed_map, targets)
from landmark_ros.mrclam.localize_data import (calibrate_odometry,
                                               format_odometry_calibration, load_all_extras,
                                               with_camera_delay)
from landmark_ros.mrclam.localize_plan import hide_ids, slice_run
from landmark_ros.mrclam.report import write_json

ASSOCIATION_KEYS = ('no_id', 'associated', 'association_ambiguous',
                    'association_unmatched', 'association_merged', 'rows_used',
                    'rows_gated')


def _sections(path):
    import yaml
    with open(path, encoding='utf-8') as stream:
        document = yaml.safe_load(stream) or {}
    return (node_section(document, 'landmark_localizer'),
            node_section(document, 'landmark_mrclam'))


class _Bar:
    """A tqdm bar on stderr when it is a terminal, else nothing."""

    def __init__(self, label):
        self._bar = None
        if sys.stderr.isatty():
            from tqdm import tqdm
            self._bar = tqdm(total=100, desc=label, leave=False, file=sys.stderr)
        self._done = 0

    def update(self, fraction):
        if self._bar is not None:
            step = int(100 * fraction) - self._done
            if step > 0:
                self._bar.update(step)
                self._done += step

    def close(self):
        if self._bar is not None:
            self._bar.close()


def localize(args, dataset, replay_config, document):
    """Run ``--localize``; return the exit code (0 also when targets fail: they print)."""
    localizer_values, replay_values = _sections(replay_config.path)
    config = localizer_config(localizer_values)
    delay_s = float(replay_values.get('odometry_delay_s', 0.0))
    dataset, extras = with_camera_delay(dataset, load_all_extras(dataset),
                                        replay_config.camera_delay_s)
    document['camera_delay_s'] = replay_config.camera_delay_s
    if args.duration is not None:
        dataset, extras = slice_run(dataset, extras, args.duration)
        document['dataset']['duration_s'] = dataset.duration
    maps = {'surveyed': surveyed_map(dataset), 'fused': fused_map(dataset, replay_config)}
    if args.hide_ids:  # the maps keep their IDs; the localizers associate the rows
        dataset = hide_ids(dataset, UNKNOWN_ID)
        document['hide_ids'] = True
    bar = None if args.no_progress else _Bar
    entries, tracks = run_all(dataset, extras, config, maps, delay_s, bar)
    print(format_table(entries, dataset.duration))
    print('targets:')
    for name, holds in targets(entries):
        print(f'  {"holds" if holds else "FAILS"}: {name}')
    # The list holds the maps only; dead reckoning (the floor) beside it.
    document['localization'] = [e for e in entries if e['map'] != 'dead_reckoning']
    document['dead_reckoning'] = next(e for e in entries if e['map'] == 'dead_reckoning')
    document['localizer_config'] = {k: (list(v) if isinstance(v, tuple) else v)
                                    for k, v in vars(config).items()}
    document['odometry_delay_s'] = delay_s
    if args.hide_ids:
        document['association'] = association_counts(tracks)
        print(format_association_counts(document['association']))
    code = 0
    if args.through_nodes:
        code = through_nodes(args, (dataset, extras, replay_config.path, maps, delay_s),
                             entries, tracks, document)
    if args.json:
        write_json(args.json, document)
        print(f'wrote {args.json}')
    if args.plot:
        from landmark_ros.mrclam.localize_plot import plot_run
        for (name, coop), result in tracks.items():
            path = Path(args.plot)
            out = path.with_name(f'{path.stem}-{name}{"-robots" if coop else ""}{path.suffix}')
            plot_run(out, dataset, result, f'MRCLAM {dataset.path.name}: {name}'
                     f'{" + robot sightings" if coop else ""} (2 sigma every 20 s)')
            print(f'wrote {out}')
    return code


def association_counts(tracks):
    """Return per run (``map``, ``cooperative``) the association counters summed over robots."""
    return [{'map': name, 'cooperative': coop,
             **{key: sum(int(t.counts.get(key, 0)) for t in result)
                for key in ASSOCIATION_KEYS}}
            for (name, coop), result in tracks.items() if name != 'dead_reckoning']


def format_association_counts(entries):
    """Return the association counters as text, one line per run."""
    lines = ['rows without ID (--hide-ids), associated by the localizers:']
    for e in entries:
        lines.append(f'  {e["map"]:9s} {"+ robots" if e["cooperative"] else "        "} '
                     + ', '.join(f'{key} {e[key]}' for key in ASSOCIATION_KEYS))
    return '\n'.join(lines)


def through_nodes(args, data, entries, tracks, document):
    """
    Run the non-cooperative runs through ``landmark_localizer`` nodes and compare.

    ``data`` is ``(dataset, extras, config_path, maps, delay_s)``. The JSON gains
    ``localization_nodes`` (the node runs, the keys of ``localization``) and
    ``localization_agreement`` (per run, ``localize_nodes.compare``). Returns 1 when
    a run does not agree (stamps or row counts differ), else 0.
    """
    import tempfile

    from landmark_ros.mrclam.localize import metrics
    from landmark_ros.mrclam.localize_nodes import compare, run_through_nodes
    from landmark_ros.mrclam.replay_plan import domain_id_for, ReplayError
    dataset, extras, config_path, maps, delay_s = data
    domain = domain_id_for() if args.domain_id is None else int(args.domain_id)
    work = Path(tempfile.mkdtemp(prefix='landmark_mrclam_localize_'))
    print(f'through the nodes: ROS_DOMAIN_ID={domain}, loopback only; logs in {work}')
    bar = None if args.no_progress else _Bar
    try:
        runs = run_through_nodes(dataset, extras, config_path, maps, delay_s, domain, work,
                                 bar)
    except (RuntimeError, ReplayError) as error:
        print(f'landmark_mrclam: {error}', file=sys.stderr)
        return 1
    node_entries, agreement, ok = [], [], True
    for name, (node_tracks, info) in runs.items():
        robots, overall = metrics(node_tracks)
        node_entries.append({'map': name, 'cooperative': False, **overall,
                             'seconds': info['play_wall_s'], 'cpu_seconds': info['node_cpu_s'],
                             'startup_s': info['startup_s'], 'robots': robots})
        agree = {'map': name, 'cooperative': False,
                 **compare(tracks[(name, False)], node_tracks)}
        offline = next(e for e in entries if e['map'] == name and not e['cooperative'])
        agree['max_metric_diff'] = max(abs(offline[k] - node_entries[-1][k])
                                       for k in ('position_rmse_m', 'heading_rmse_rad',
                                                 'anees', 'inside_95_fraction'))
        agreement.append(agree)
        ok &= agree['same_stamps'] and agree['same_counts']
    print('through the nodes:')
    print(format_table(node_entries, dataset.duration))
    print('agreement with the offline run:')
    for a in agreement:
        print(f'  {a["map"]:15s} same stamps {a["same_stamps"]}, same rows {a["same_counts"]}, '
              f'max position diff {a["max_position_diff_m"]:.3g} m, heading '
              f'{a["max_heading_diff_rad"]:.3g} rad, covariance {a["max_cov_diff"]:.3g}, '
              f'figures {a["max_metric_diff"]:.3g}')
    document['mode'] = 'through_nodes'
    document['localization_nodes'] = [e for e in node_entries if e['map'] != 'dead_reckoning']
    document['dead_reckoning_nodes'] = node_entries[0]
    document['localization_agreement'] = agreement
    if ok:
        import shutil
        shutil.rmtree(work, ignore_errors=True)
    return 0 if ok else 1


def calibrate(args, dataset, replay_config, document):
    """Run ``--calibrate-odometry``; return the exit code."""
    localizer_values, _ = _sections(replay_config.path)
    period_s = localizer_config(localizer_values).odometry_alphas_period_s
    result = calibrate_odometry(dataset, load_all_extras(dataset), period_s=period_s)
    print(format_odometry_calibration(result))
    if args.json:
        document['odometry_calibration'] = result
        write_json(args.json, document)
    return 0
