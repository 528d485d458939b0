"""
Summarise benchmark outputs in one table, on stdout and as markdown.

Every benchmark prints a last, machine-readable line::

    RESULT <name> key=value key=value ...

This reads those lines from the given logs (or stdin), whatever benchmark printed
them, and prints one table: core throughput and its ratio to the chapter-style loop,
the pipeline objects' cost per message, node message rates next to the relay, replay
speed-up over real time (any key naming a speed-up or a real-time factor, from any
benchmark), peak memory, and the targets; keys of benchmarks it does not know are
listed generically (throughputs, rates, ratios, speed-ups, memory). The machine
(``_common.machine``: CPU model, cores, Python and numpy versions, commit) heads the
table. ``--markdown PATH`` also writes the table as a markdown page of the manual
(``make bench`` writes ``docs/benchmarks.md``, the latest run only; it says it is
generated and carries no date: the commit names the run).

Usage: ``python bench/summary.py [--markdown PATH] [LOG ...]``.
"""

import argparse
import datetime
import os
import re
import sys

import _common

RESULT_LINE = re.compile(r'^RESULT\s+(\S+)((?:\s+\S+=\S*)*)\s*$')
SPEED_UP_KEY = re.compile(r'speed_?up|real_?time|rtf', re.IGNORECASE)
MEMORY_KEY = re.compile(r'(?:peak_rss|maxrss)_(.+)_mb$')
GENERIC_KEY = re.compile(r'obs_per_s|msg_per_s|per_s$|ratio|speed|real_?time|_mb$|lag',
                         re.IGNORECASE)
FUSIONS = (('independent', 'independent'), ('ci', 'covariance intersection'),
           ('split_ci', 'split covariance intersection'))
KNOWN = ('bench_core', 'bench_fuser', 'bench_observer', 'bench_localizer')


def parse(lines):
    """
    Return the RESULT lines' figures.

    Parameters
    ----------
    lines : iterable of str
        Benchmark output.

    Returns
    -------
    dict
        ``name -> {key: value}``, values as float where they parse, else str; a later
        line of the same name replaces an earlier one.

    """
    results = {}
    for line in lines:
        match = RESULT_LINE.match(line.strip())
        if not match:
            continue
        values = {}
        for item in match.group(2).split():
            key, _, value = item.partition('=')
            try:
                values[key] = float(value)
            except ValueError:
                values[key] = value
        results[match.group(1)] = values
    return results


def si(value, unit=''):
    """Format a number with a k/M/G prefix and three significant digits."""
    if not isinstance(value, float):
        return f'{value} {unit}'.strip()
    for factor, prefix in ((1e9, 'G'), (1e6, 'M'), (1e3, 'k')):
        if abs(value) >= factor:
            return f'{value / factor:.3g} {prefix} {unit}'.strip()
    return f'{value:.3g} {unit}'.strip()


def _num(value, digits=3):
    return f'{value:.{digits}g}' if isinstance(value, float) else str(value)


def rows_for(results):
    """
    Return the table rows.

    Returns
    -------
    list of (section, what, figure, context, source)

    """
    rows = []
    core = results.get('bench_core', {})
    if 'vectorised_obs_per_s' in core:
        rows.append(('core', 'landmark_to_world, per-observation covariances',
                     si(core['vectorised_obs_per_s'], 'obs/s'),
                     f'{_num(core.get("ratio"))}x the chapter-style loop '
                     f'({si(core.get("loop_obs_per_s"), "obs/s")})', 'bench_core'))
    if 'shared_vectorised_obs_per_s' in core:
        rows.append(('core', 'landmark_to_world, shared covariances',
                     si(core['shared_vectorised_obs_per_s'], 'obs/s'),
                     f'{_num(core.get("shared_ratio"))}x the chapter-style loop '
                     f'({si(core.get("shared_loop_obs_per_s"), "obs/s")})', 'bench_core'))
    fuser = results.get('bench_fuser', {})
    observer = results.get('bench_observer', {})
    for rows_per_msg in (1, 10, 100):
        key = f'pipeline_add_us_{rows_per_msg}'
        if key in observer:
            rows.append(('pipeline', f'Observer.add_observations, {rows_per_msg} rows/msg',
                         f'{_num(observer[key])} us/msg', 'thread CPU time; of which place '
                         f'{_num(observer.get(f"pipeline_place_us_{rows_per_msg}"))} us',
                         'bench_observer'))
    for short, name in FUSIONS:
        key = f'pipeline_{short}_add_us'
        if key in fuser:
            rows.append(('pipeline', f'Fuser, {name}, 100 rows/msg',
                         f'{_num(fuser[key] + fuser.get(f"pipeline_{short}_fuse_us", 0.0))} '
                         'us/msg', 'thread CPU time: add_landmark_messages (16 messages per '
                         f'call) {_num(fuser[key])} us + '
                         f'fuse_queued {_num(fuser.get(f"pipeline_{short}_fuse_us"))} us',
                         'bench_fuser'))
    plain, detection = (fuser.get(f'pipeline_{k}_fuse_us') for k in ('no_detection', 'split_ci'))
    if detection and plain:
        rows.append(('pipeline', 'Fuser, split covariance intersection without change '
                     'detection, 100 rows/msg', f'{_num(plain)} us/msg', 'fuse_queued '
                     f'only (detection is on by default); with it {_num(detection / plain)}x',
                     'bench_fuser'))
    for rows_per_msg in (1, 10, 100):
        key = f'observer_msg_per_s_{rows_per_msg}'
        if key in observer:
            rows.append(('node', f'landmark_observer, {rows_per_msg} rows/msg',
                         si(observer[key], 'msg/s'),
                         f'{_num(observer.get(f"ratio_{rows_per_msg}"))} x relay '
                         f'({si(observer.get(f"relay_msg_per_s_{rows_per_msg}"), "msg/s")}); '
                         f'CPU-time ratio relay/observer '
                         f'{_num(observer.get(f"cpu_ratio_{rows_per_msg}"))}',
                         'bench_observer'))
    for short, name in FUSIONS:
        key = f'fuser_{short}_msg_per_s_100'
        if key in fuser:
            rows.append(('node', f'landmark_fuser, {name}, 100 rows/msg',
                         si(fuser[key], 'msg/s'),
                         f'{_num(fuser.get(f"ratio_{short}_100"))} x relay '
                         f'({si(fuser.get("relay_msg_per_s_100"), "msg/s")}); CPU-time ratio '
                         f'relay/fuser {_num(fuser.get(f"cpu_ratio_{short}"))}', 'bench_fuser'))
        if f'lag_{short}_ms' in fuser:
            rows.append(('node', f'landmark_fuser, {name}: fusion lag',
                         f'{_num(fuser[f"lag_{short}_ms"])} ms',
                         'last input -> queues empty after a fusion (in the node); end to end to '
                         f'fused_landmarks {_num(fuser.get(f"e2e_lag_{short}_ms"))} ms',
                         'bench_fuser'))
    rows += localizer_rows(results.get('bench_localizer', {}))
    for short, name in (('split_ci_50_sources', 'split CI, 50 input topics, every robot '
                         'seeing every landmark'),
                        ('split_ci_50_sources_local', 'split CI, 50 input topics, each robot '
                         'seeing its 100 nearest landmarks')):
        key = f'fuser_{short}_msg_per_s_100'
        if key in fuser:
            rows.append(('node', f'landmark_fuser, {name}, 100 rows/msg',
                         si(fuser[key], 'msg/s'),
                         f'{_num(fuser.get(f"ratio_{short}_100"))} x relay on the 50 topics '
                         f'({si(fuser.get("relay_50_sources_msg_per_s_100"), "msg/s")}); '
                         f'CPU-time ratio relay/fuser {_num(fuser.get(f"cpu_ratio_{short}"))}',
                         'bench_fuser'))
    for name, values in results.items():
        for key, value in values.items():
            if SPEED_UP_KEY.search(key):
                rows.append(('replay', f'{name}: {key}', f'{_num(value)}x'
                             if isinstance(value, float) else str(value),
                             'speed-up over real time', name))
    for name, values in results.items():
        for key, value in values.items():
            match = MEMORY_KEY.search(key)
            if match and isinstance(value, float):
                rows.append(('memory', f'peak RSS, {match.group(1).replace("_", " ")}',
                             f'{value:.0f} MB', 'maxrss' if key.startswith('maxrss') else
                             'VmHWM of the process', name))
    for name, values in results.items():
        if name in KNOWN:
            continue
        for key, value in values.items():
            if GENERIC_KEY.search(key) and not SPEED_UP_KEY.search(key) \
                    and not MEMORY_KEY.search(key):
                rows.append(('other', f'{name}: {key}', _num(value), '', name))
    rows += floor_rows(results)
    for name, values in results.items():
        if 'pass' in values:
            rows.append(('targets', name, 'all met' if values['pass'] == 1.0 else
                         'not all met', 'PASS/FAIL per target in its log', name))
    return rows


def localizer_rows(loc):
    """Return the rows of ``bench_localizer``: pipeline costs, node against its relay."""
    rows = []
    if 'odometry_us' in loc:
        rows.append(('pipeline', 'Localizer.add_odometry', f'{_num(loc["odometry_us"])} us/msg',
                     'thread CPU time', 'bench_localizer'))
    cases = [(f'{correlation}_{when}_row_us', f'{correlation}, {what}', '')
             for correlation in ('independent', 'split_ci', 'consider')
             for when, what in (('now', 'at the newest odometry'), ('late', '0.5 s late'))]
    cases += [(f'split_ci_noid_{hidden}_now_row_us', f'rows without ID, {what}',
               'map of pairs 0.3 m apart, ')
              for hidden, what in (('take', "JCBB's choice"), ('merge', 'applied per candidate'))]
    for key, what, setting in cases:
        if key in loc:
            rows.append(('pipeline', f'Localizer.add_observations, {what}',
                         f'{_num(loc[key])} us/row', f'thread CPU time, {setting}batches of '
                         f'{_num(loc.get("rows"))} rows', 'bench_localizer'))
    if 'localizer_msg_per_s' in loc:
        rows.append(('node', 'landmark_localizer, odometry (a sighting batch every 5th)',
                     si(loc['localizer_msg_per_s'], 'msg/s'),
                     f'{_num(loc.get("node_ratio"))} x relay '
                     f'({si(loc.get("relay_msg_per_s"), "msg/s")}); CPU/msg localizer '
                     f'{_num(loc.get("localizer_cpu_us_per_msg"))} us, relay '
                     f'{_num(loc.get("relay_cpu_us_per_msg"))} us', 'bench_localizer'))
    return rows


PAGE_HEAD = """\
# Benchmarks

<!-- Generated by `make bench` (bench/summary.py) from the benchmarks' RESULT lines: the
latest run only. Do not edit by hand; re-run `make bench`. -->

`make bench` runs every `bench/bench_*.py` (each log in `bench/results/`) and writes
this page. The benchmarks time public methods only, nothing wrapped or patched:
`bench_core.py` the core functions against a chapter-style per-observation loop;
`bench_observer.py` and `bench_fuser.py` the pipeline objects without ROS (thread CPU
time), then the nodes over DDS next to a bare relay node in the same run (closed loop;
ratios above 1 mean faster than the relay); `bench_fuser.py` also a split-CI fuser on
50 input topics next to a relay on the same 50 topics; `bench_map.py`
`LandmarkMap.update` on big batches, the three fusion methods side by side;
`bench_association.py` data association into 10,000 landmarks; `bench_outputs.py` what
the fuser publishes at 10,000 landmarks; `bench_localizer.py` the localizer's cost per
odometry message and per sighting row, its node next to a relay node in the same run,
and the MRCLAM localization replay's real-time factor. Each benchmark prints PASS or
FAIL per target in its log. On a shared machine message rates vary from run to run; ratios measured
side by side hold better than absolute rates.
"""


FLOORS = (('bench_map', 'split_ci_1000_ratio', 0.5,
           'split CI / independent, 1,000 landmarks, 5 sources'),
          ('bench_map', 'split_ci_10000_ratio', 0.5,
           'split CI / independent, 10,000 landmarks, 50 sources'),
          ('bench_fuser', 'ratio_split_ci_100', 0.8,
           'split-CI fuser node / relay, 100 rows/msg'),
          ('bench_fuser', 'ratio_split_ci_50_sources_100', 0.7,
           'split-CI fuser node / relay, 50 topics, every robot every landmark'))
"""The floors of the split-CI stack: (benchmark, RESULT key, least ratio, what)."""


def floor_rows(results):
    """Return one row per floor: the ratio of this run, the floor, PASS or FAIL."""
    rows = []
    for name, key, floor, what in FLOORS:
        value = results.get(name, {}).get(key)
        verdict = ('not run' if not isinstance(value, float) else
                   'PASS' if value >= floor else 'FAIL')
        rows.append(('floors', what, _num(value) if isinstance(value, float) else '-',
                     f'floor {floor:g}x: {verdict}', name))
    return rows


def render(results, host, missing, markdown):
    """Return the summary as text (``markdown`` False) or markdown."""
    header = ('section', 'what', 'figure', 'context', 'from')
    rows = rows_for(results)
    machine = (f'{host["cpu"]}, {host["cpu_count"]} cores, {host["platform"]}, Python '
               f'{host["python"]}, numpy {host["numpy"]}; commit {host["commit"]}')
    load = f'load average {host["load"]:.1f} when summarised'
    notes = [f'no RESULT line from {name}: see its log' for name in missing]
    if not results:
        notes.append('no RESULT lines found')
    if markdown:
        lines = [PAGE_HEAD, f'Machine: {machine}; {load}.', '',
                 '| ' + ' | '.join(header) + ' |',
                 '| ' + ' | '.join('---' for _ in header) + ' |']
        lines += ['| ' + ' | '.join(cell.replace('|', '\\|') for cell in row) + ' |'
                  for row in rows]
        lines += [''] + [f'- {note}' for note in notes]
        return '\n'.join(lines).rstrip() + '\n'
    when = datetime.datetime.now().strftime('%Y-%m-%d %H:%M')
    machine_line = f'{machine}; {when}; {load}'
    widths = [max(len(str(row[i])) for row in [header] + rows) for i in range(len(header))]
    widths[3] = min(widths[3], 80)
    lines = ['=' * 30 + ' benchmark summary ' + '=' * 30, f'machine: {machine_line}']
    lines.append('  '.join(h.ljust(w) for h, w in zip(header, widths)).rstrip())
    lines.append('  '.join('-' * w for w in widths))
    for row in rows:
        lines.append('  '.join(str(c).ljust(w) for c, w in zip(row, widths)).rstrip())
    lines += notes
    return '\n'.join(lines) + '\n'


def main(argv=None):
    """Read the logs, print the summary, write the markdown; return the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('logs', nargs='*', help='benchmark logs (default: stdin)')
    parser.add_argument('--markdown', metavar='PATH',
                        help='also write the summary as markdown to PATH')
    args = parser.parse_args(argv)
    results, missing = {}, []
    if args.logs:
        for path in args.logs:
            try:
                with open(path, encoding='utf-8', errors='replace') as stream:
                    found = parse(stream)
            except OSError as error:
                print(f'summary: cannot read {path}: {error}', file=sys.stderr)
                found = {}
            if not found:
                missing.append(os.path.splitext(os.path.basename(path))[0])
            results.update(found)
    else:
        results = parse(sys.stdin)
    host = _common.machine()
    sys.stdout.write(render(results, host, missing, markdown=False))
    if args.markdown:
        with open(args.markdown, 'w', encoding='utf-8') as stream:
            stream.write(render(results, host, missing, markdown=True))
        print(f'summary written to {args.markdown}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
