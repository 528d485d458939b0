"""
The ``--localize`` and ``--calibrate-odometry`` modes of ``landmark_mrclam``.

``--localize``: ``mrclam.localize.run_all`` with the ``landmark_localizer`` section of the
params file (``config/mrclam.yaml``: the calibrated sensor and odometry models) and the
odometry delay of its ``landmark_mrclam`` section; prints the per-robot table and which
of the issue's targets hold; ``--json`` gains ``localization`` (one entry per map and
mode), ``--plot FILE`` draws one picture per run
(``FILE`` stem + ``-MAP[-robots]``). Dead reckoning is the JSON's ``dead_reckoning``
entry (same keys), beside the ``localization`` list.

``--calibrate-odometry``: the odometry delay and alphas from the ground truth with the
leave-one-robot-out cross-check (``localize_data.calibrate_odometry``).
"""

from pathlib import Path
import sys

from landmark_ros.mrclam.config import node_section
from landmark_ros.mrclam.localize import (format_table, fused_map, localizer_config,
                                          run_all, surveyed_map, targets)
from landmark_ros.mrclam.localize_data import (calibrate_odometry,
                                               format_odometry_calibration, load_all_extras)
from landmark_ros.mrclam.report import write_json


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
    extras = load_all_extras(dataset)
    maps = {'surveyed': surveyed_map(dataset), 'fused': fused_map(dataset, replay_config)}
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
    return 0


def calibrate(args, dataset, document):
    """Run ``--calibrate-odometry``; return the exit code."""
    result = calibrate_odometry(dataset, load_all_extras(dataset))
    print(format_odometry_calibration(result))
    if args.json:
        document['odometry_calibration'] = result
        write_json(args.json, document)
    return 0
