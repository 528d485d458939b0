"""
landmark_bag: run a recorded bag through the landmark pipeline offline, faster than real time.

::

    landmark_bag INPUT -o OUTPUT [--storage {mcap,sqlite3}] [--config PARAMS_FILE]
                 [--json FILE] [--robots NAMES] [--no-progress]
    landmark_bag --from-mrclam DATASET -o OUTPUT [--config PARAMS_FILE]

``INPUT`` is a rosbag2 (directory, ``.mcap`` or ``.db3``) with ``/<robot>/pose`` and
``/<robot>/observations`` per robot (the observers' inputs; robots are found by the
topics ``/<name>/observations`` unless ``--robots`` lists them). ``OUTPUT`` is the bag
directory to create with what the nodes would have published
(``landmark_ros.bag.process``), in the storage ``--storage`` names (``mcap``, Jazzy's
default, or ``sqlite3``; by default the input's, as ``ros2 bag`` users expect).
``--config`` is the parameter file the nodes take with ``--params-file``: its
``landmark_observer`` sections (node-name keys as ROS matches them, ``/**:`` included)
configure each robot's observer, its ``landmark_fuser`` sections the fuser. When the
bag holds ``/ground_truth_landmarks`` the fused map is evaluated as ``landmark_mrclam``
does (``--json`` writes ``{"input", "output", "robots", "speedup", "summary": [entry]}``,
the entry as in the replay's JSON).

``--from-mrclam DATASET`` writes a MRCLAM dataset directory as such a bag instead
(``landmark_ros.bag.export``: poses, observations, ``/ground_truth_landmarks``; the pose
standard deviations from the ``landmark_mrclam`` section of ``--config``) and stops.

Exit codes: 0 the input bag was whole and everything was written; 3 the bag was
damaged (an unreadable record or chunk, an undecodable message, fewer messages than
its metadata lists): the readable part was processed, the output bag is complete for
it, and the summary and the JSON (``input_damage``, ``messages_expected``,
``messages_read``) count what was skipped by reason; 2 a bag that cannot be used
(missing, cut before its index, a missing topic, a topic of another message type),
an invalid parameter or an existing output: one line, no output left behind; 130
interrupted.
"""

import argparse
import json
from pathlib import Path
import sys

from landmark_ros.bag.export import export_dataset, pose_stddev_from_config
from landmark_ros.bag.params import read_document
from landmark_ros.bag.process import process_bag
from landmark_ros.bag.report import evaluate_map, format_report
from landmark_ros.bag.storage import BagError, STORAGES
from landmark_ros.mrclam.data import DEFAULT_POSE_STDDEV

PROG = 'landmark_bag'
EXIT_DAMAGED = 3
"""Exit code of a damaged input bag processed as far as it could be read."""


def parse_args(argv=None):
    """Parse the command line (argparse exits with code 2 on a usage error)."""
    parser = argparse.ArgumentParser(
        prog=PROG, description='Run a recorded bag through landmark_observer (one per robot) '
        'and landmark_fuser offline; write their outputs as a bag.')
    parser.add_argument('input', type=Path, nargs='?', default=None,
                        help='input rosbag2 (directory, .mcap or .db3)')
    parser.add_argument('--from-mrclam', type=Path, default=None, metavar='DATASET',
                        help='instead of INPUT: write the MRCLAM dataset directory DATASET '
                             'as a bag OUTPUT and stop')
    parser.add_argument('-o', '--output', type=Path, required=True,
                        help='output bag directory to create (must not exist)')
    parser.add_argument('--storage', choices=sorted(STORAGES), default=None,
                        help="storage of the output bag (default: the input's)")
    parser.add_argument('--config', type=Path, default=None, metavar='PARAMS_FILE',
                        help='ROS parameter file with landmark_observer and landmark_fuser '
                             'sections (as for --params-file); default: the parameter '
                             'defaults')
    parser.add_argument('--json', type=Path, default=None, metavar='FILE',
                        help='write the run and, with ground truth, the evaluation as JSON')
    parser.add_argument('--robots', default=None, metavar='NAMES',
                        help='robot names separated by commas or spaces (default: every '
                             '<name> with a topic /<name>/observations)')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')
    args = parser.parse_args(argv)
    if (args.input is None) == (args.from_mrclam is None):
        parser.error('give either INPUT or --from-mrclam DATASET')
    return args


def export_mrclam(dataset, output, config):
    """Write a MRCLAM dataset as a bag (``--from-mrclam``); return the exit code."""
    try:
        stddev = (pose_stddev_from_config(config) if config is not None
                  else DEFAULT_POSE_STDDEV)
        counts = export_dataset(dataset, stddev, output)
    except (BagError, OSError, ValueError) as error:
        print(f'{PROG}: error: {error}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f'{PROG}: interrupted: no bag written', file=sys.stderr)
        return 130
    total = sum(counts.values())
    print(f'wrote {output}: {total} messages on {len(counts)} topics '
          f'(then: {PROG} {output} -o OUTPUT --config PARAMS_FILE)')
    return 0


def _progress_bar(enabled):
    """
    Return ``(callback, close)`` driving a tqdm bar on stderr (or doing nothing).

    ``enabled``: False never draws; True draws only when stderr is a terminal (nothing
    in logs and pipes), as the replay's and the demo's bars.
    """
    if not enabled or not sys.stderr.isatty():
        return None, lambda: None
    from tqdm import tqdm
    bar = tqdm(total=0, unit='msg', unit_scale=True, file=sys.stderr, desc=PROG,
               dynamic_ncols=True)

    def update(done, total):
        if bar.total != total:
            bar.total = total
            bar.refresh()
        bar.update(done - bar.n)

    return update, bar.close


def main(argv=None):
    """Run ``landmark_bag``; return the exit code."""
    args = parse_args(argv)
    if args.from_mrclam is not None:
        return export_mrclam(args.from_mrclam, args.output, args.config)
    robots = None
    if args.robots is not None:
        robots = [name.strip('/') for name in args.robots.replace(',', ' ').split()]
        if not robots:
            print(f'{PROG}: error: --robots names no robot', file=sys.stderr)
            return 2
    update, close = _progress_bar(not args.no_progress)
    try:
        document = read_document(args.config) if args.config is not None else None
        result = process_bag(args.input, args.output, document, robots, update, args.storage)
    except (BagError, ValueError) as error:
        close()
        print(f'{PROG}: error: {error}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        close()
        print(f'{PROG}: interrupted: no output written', file=sys.stderr)
        return 130
    close()
    counts = ', '.join(f'{topic} {count}' for topic, count in sorted(result.counts.items()))
    print(f'{result.messages_in} messages of {len(result.robots)} robots '
          f'({", ".join(result.robots)}), {result.bag_duration_s:.1f} s of bag time in '
          f'{result.wall_s:.2f} s ({result.cpu_s:.2f} s CPU): {result.speedup:.0f} x real time')
    print(f'wrote {args.output}: {counts}')
    if result.damage:
        damage = ', '.join(f'{reason} {count}' for reason, count in sorted(result.damage.items()))
        print(f'input damaged: read {result.messages_in} of {result.messages_expected} '
              f'messages the metadata lists; skipped: {damage}')
    document = {'input': str(args.input), 'output': str(args.output), 'robots': result.robots,
                'bag_duration_s': result.bag_duration_s, 'wall_s': result.wall_s,
                'cpu_s': result.cpu_s, 'messages_out': result.counts,
                'speedup': result.speedup if result.wall_s > 0.0 else None,
                'messages_expected': result.messages_expected,
                'messages_read': result.messages_in, 'input_damage': result.damage}
    if result.truth is not None:
        entry, results, summary = evaluate_map(result.fuser, result.truth)
        print()
        print(format_report(entry, results, summary))
        document['summary'] = [entry]
    else:
        print('no /ground_truth_landmarks in the bag: no evaluation')
    if args.json is not None:
        try:
            with open(args.json, 'w', encoding='utf-8') as stream:
                json.dump(document, stream, indent=1, allow_nan=False)
                stream.write('\n')
        except (OSError, ValueError) as error:
            print(f'{PROG}: error: cannot write {args.json}: {error}', file=sys.stderr)
            return 2
    return EXIT_DAMAGED if result.damage else 0


if __name__ == '__main__':
    sys.exit(main())
