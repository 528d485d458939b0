"""
What the replay reports: per-method results, tables, JSON, the plot (ROS-free).

``method_result`` evaluates a fused map against the true landmarks
(``landmark_ros.eval.metrics``); ``report`` and ``summary_table`` print the results,
``MethodResult.to_dict`` and ``dataset_dict`` make the JSON document ``write_json``
writes, ``agreement`` compares the maps of the offline and through-the-nodes runs, and
``plot`` draws the maps (matplotlib, optional).
"""

from dataclasses import dataclass, replace
import json
import math

from landmark_ros.eval import metrics as evaluation
import numpy as np


# Results -------------------------------------------------------------------------------

@dataclass
class MethodResult:
    """One fusion method's map against the ground truth."""

    fusion: str
    records: list
    """The confirmed landmarks, as ``LandmarkMap.to_records`` gives them."""
    results: list
    """``evaluation.LandmarkResult`` per landmark with a true position."""
    summary: object
    """``evaluation.Summary``."""
    observations_used: int
    """Observations fused (accepted) over the run."""
    observations_rejected: int
    """Observations gated out or left out of a confirmation."""
    sensor: str = 'rb'
    """Which columns the replay kept: ``rb`` (range-bearing), ``range`` or ``bearing``."""
    landmarks_initialised: int = 0
    """Landmarks placed from partial observations (``fuser.partial``)."""
    association: object = None
    """``eval.metrics.AssociationSummary`` of a run without IDs (``--hide-ids``), else None."""
    moves: object = None
    """``(alarms, rows tested)`` of the fuser's change detection (None: off or not known)."""

    def to_dict(self):
        """Return the JSON summary entry, with the landmarks inside."""
        by_id = {r.id: r for r in self.results}
        landmarks = []
        for record in self.records:
            result = by_id.get(record['id'])
            landmarks.append({
                'id': int(record['id']), 'x': record['mean'][0], 'y': record['mean'][1],
                'cov': np.asarray(record['covariance'], dtype=float).reshape(2, 2).tolist(),
                'error_m': None if result is None else result.error_m,
                'nees': None if result is None else result.nees,
                'observations': int(record['observations']),
                'rejections': int(record.get('rejections', 0))})
        low, high = self.summary.anees_interval
        return {'fusion': self.fusion, 'sensor': self.sensor,
                'landmarks_initialised': int(self.landmarks_initialised),
                'rmse_m': _number(self.summary.rmse_m),
                'anees': _number(self.summary.anees),
                'anees_interval': [_number(low), _number(high)],
                'consistent': bool(self.summary.consistent),
                'landmarks_fused': len(self.records),
                'observations_used': int(self.observations_used),
                'observations_rejected': int(self.observations_rejected),
                **({} if self.association is None else self.association.to_dict()),
                **({} if self.moves is None else {'move_alarms': int(self.moves[0]),
                                                  'move_tested_rows': int(self.moves[1])}),
                'landmarks': landmarks}


def _number(value):
    return None if value is None or not math.isfinite(value) else float(value)


def method_result(fusion, records, truth, used, rejected):
    """Evaluate map records against ``truth`` (id -> (x, y))."""
    records = sorted(records, key=lambda r: r['id'])
    ids = np.array([r['id'] for r in records], dtype=np.int64)
    m = np.array([r['mean'] for r in records], dtype=np.float64).reshape(-1, 2)
    P = np.array([r['covariance'] for r in records], dtype=np.float64).reshape(-1, 2, 2)
    results, summary = evaluation.evaluate(
        ids, m, P, truth, [r['observations'] for r in records],
        [r.get('rejections', 0) for r in records])
    return MethodResult(fusion, records, results, summary, used, rejected)


# Reports ---------------------------------------------------------------------------------

def summary_table(results):
    """Return one line per method: landmarks, RMSE, average NEES and its interval."""
    lines = [f"{'fusion':<30} {'landmarks':>9} {'RMSE [cm]':>9} {'ANEES':>9} "
             f"{'95 % interval':>15} {'consistent':>10} {'used':>7} {'rejected':>8}"]
    for result in results.values():
        s = result.summary
        low, high = s.anees_interval
        lines.append(f'{result.fusion:<30} {len(result.records):9d} {100 * s.rmse_m:9.2f} '
                     f'{s.anees:9.2f} {f"[{low:.2f}, {high:.2f}]":>15} '
                     f"{'yes' if s.consistent else 'no':>10} {result.observations_used:7d} "
                     f'{result.observations_rejected:8d}')
    return '\n'.join(lines)


def report(results):
    """Return the per-method tables and the summary table."""
    parts = []
    for result in results.values():
        parts.append(evaluation.format_table(
            result.results, result.summary,
            f'== {result.fusion}: {len(result.records)} landmarks, '
            f'{result.observations_used} observations fused, '
            f'{result.observations_rejected} rejected' + _moves(result.moves)))
    parts.append('== summary\n' + summary_table(results))
    return '\n\n'.join(parts)


def _moves(moves):
    """Return the change detection's alarms as a phrase ('' when off)."""
    if moves is None:
        return ''
    alarms, tested = moves
    return (f'; change detection: {alarms} alarms in {tested} tested rows '
            f'({1e4 * alarms / max(tested, 1):.2f} per 10,000)')


def format_association(results):
    """Return the association scores of runs without IDs and their confusions."""
    lines = [f"{'fusion':<30} {'accuracy':>8} {'oracle':>8} {'tracks':>6} {'true':>5} "
             f"{'GOSPA [m]':>9}"]
    for result in results.values():
        a = result.association
        if a is None:
            continue
        lines.append(f'{result.fusion:<30} {100 * a.association_accuracy:7.2f}% '
                     f'{100 * a.oracle_accuracy:7.2f}% {a.tracks_confirmed:6d} '
                     f'{a.true_landmarks:5d} {a.gospa_m:9.3f}')
        wrong = sorted(a.confusion.items(), key=lambda item: -item[1])[:8]
        lines.append('  most confused (true -> went to, -1 = no matched track): ' + ', '.join(
            f'{t}->{w}: {n}' for (t, w), n in wrong))
    return '== association (IDs hidden)\n' + '\n'.join(lines)


def dataset_report(dataset):
    """Return what was read and dropped."""
    c = dataset.counts
    start, end = dataset.time_span
    robots = ', '.join(f'{r.name} {len(r.times)}' for r in dataset.robots)
    return (f'dataset {dataset.path}: {len(dataset.robots)} robots, '
            f'{len(dataset.landmarks)} true landmarks, {dataset.duration:.1f} s of '
            f'sightings\n  measurements read {c["read"]}, kept {c["kept"]} ({robots}); '
            f'dropped: robot sightings {c["robot_sightings"]}, unknown barcodes '
            f'{c["unknown_barcode"]}, outside ground truth {c["outside_groundtruth"]}')


def dataset_dict(dataset):
    """Return the dataset description for the JSON output."""
    return {'path': str(dataset.path), 'robots': [r.name for r in dataset.robots],
            'duration_s': dataset.duration, 'counts': dict(dataset.counts),
            'landmarks_true': len(dataset.landmarks)}


def write_json(path, document):
    """Write ``document`` as indented JSON."""
    with open(path, 'w', encoding='utf-8') as stream:
        json.dump(document, stream, indent=1, allow_nan=False)
        stream.write('\n')


# Plot ------------------------------------------------------------------------------------

PLOT_COLOURS = {'independent': 'tab:red', 'covariance_intersection': 'tab:green',
                'split_covariance_intersection': 'tab:blue'}


def plot(path, dataset, results, title='MRCLAM'):
    """
    Draw the map and, beside it, every landmark's estimates around its true position.

    Left: the ground-truth robot paths, the true landmarks with their IDs and the fused
    landmarks with 2-sigma ellipses, per method. Right: one small panel per landmark
    with a true position, centred on it in centimetres, where the ellipses can be told
    apart.

    Raises
    ------
    landmark_ros.eval.plotting.PlotUnavailableError
        If matplotlib is not installed.

    """
    from landmark_ros.eval import plotting
    fig, ax = plotting.new_figure((16.0, 9.0))
    ax.set_position([0.05, 0.07, 0.45, 0.86])
    for robot in dataset.robots:
        step = max(1, len(robot.gt_times) // 4000)
        ax.plot(robot.gt_poses[::step, 0], robot.gt_poses[::step, 1], linewidth=0.5,
                alpha=0.35, color='0.45')
    ax.plot([], [], linewidth=0.5, color='0.45', label='robot paths (ground truth)')
    ids = sorted(dataset.landmarks)
    truth = np.array([dataset.landmarks[i] for i in ids]).reshape(-1, 2)
    ax.plot(truth[:, 0], truth[:, 1], 'k+', markersize=10, label='true landmarks')
    for landmark_id, (x, y) in zip(ids, truth):
        ax.annotate(str(landmark_id), (x, y), xytext=(4, 4), textcoords='offset points',
                    fontsize='small')
    reach = 1.0
    for method, result in results.items():
        colour = PLOT_COLOURS.get(method, 'tab:purple')
        for i, record in enumerate(result.records):
            plotting.draw_ellipse(ax, record['mean'], record['covariance'], 2.0, color=colour,
                                  linewidth=1.0,
                                  label=f'{method} (2 sigma)' if i == 0 else None)
            if record['id'] in dataset.landmarks:
                error = np.subtract(record['mean'], dataset.landmarks[record['id']])
                sd = math.sqrt(max(np.linalg.eigvalsh(np.asarray(record['covariance']))))
                reach = max(reach, 100.0 * (np.abs(error).max() + 2.0 * sd))
    ax.set_title(title)
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    ax.set_aspect('equal', adjustable='datalim')
    ax.grid(True, alpha=0.4)
    ax.legend(loc='best', fontsize='small')
    # One panel per landmark, in centimetres around the true position.
    columns = max(1, math.ceil(math.sqrt(len(ids))))
    rows = max(1, math.ceil(len(ids) / columns))
    width, height = 0.43 / columns, 0.86 / rows
    reach = min(1.1 * reach, 100.0)
    for k, landmark_id in enumerate(ids):
        row, column = divmod(k, columns)
        panel = fig.add_axes([0.55 + column * width + 0.1 * width,
                              0.93 - (row + 1) * height + 0.15 * height,
                              0.8 * width, 0.7 * height])
        panel.plot([0.0], [0.0], 'k+', markersize=8)
        for method, result in results.items():
            colour = PLOT_COLOURS.get(method, 'tab:purple')
            for record in result.records:
                if record['id'] != landmark_id:
                    continue
                offset = 100.0 * np.subtract(record['mean'], dataset.landmarks[landmark_id])
                plotting.draw_ellipse(panel, offset, 1e4 * np.asarray(record['covariance']),
                                      2.0, color=colour, linewidth=1.0)
                panel.plot(offset[0], offset[1], '.', color=colour, markersize=4)
        panel.set_xlim(-reach, reach)
        panel.set_ylim(-reach, reach)
        panel.set_aspect('equal')
        panel.set_title(f'{landmark_id} [cm]', fontsize='x-small', pad=2)
        panel.tick_params(labelsize='xx-small')
        panel.grid(True, alpha=0.3)
    fig.savefig(path, dpi=110)


# Agreement of the two modes ------------------------------------------------------------

def agreement(offline, nodes):
    """
    Compare the maps of both modes, per method.

    Returns
    -------
    dict
        Method -> ``same_ids``, ``same_counts`` (observations and rejections per
        landmark, used and rejected totals), ``max_mean_diff_m``,
        ``max_cov_diff_m2``, ``max_cov_dep_diff_m2``; without IDs (records with a
        ``track_id``, ``--hide-ids``) also ``same_track_ids``: the fusers' own track
        IDs equal, matched to the same true landmarks.

    """
    document = {}
    for method, node_result in nodes.items():
        a = {r['id']: r for r in offline[method].records}
        b = {r['id']: r for r in node_result.records}
        entry = {'same_ids': sorted(a) == sorted(b)}
        common = sorted(set(a) & set(b))

        def diff(key):
            if not common:
                return 0.0
            return float(max(np.max(np.abs(np.asarray(a[i][key]) - np.asarray(b[i][key])))
                             for i in common))
        entry['max_mean_diff_m'] = diff('mean')
        entry['max_cov_diff_m2'] = diff('covariance')
        entry['max_cov_dep_diff_m2'] = diff('covariance_dependent')
        entry['same_counts'] = bool(
            all(a[i]['observations'] == b[i]['observations']
                and a[i]['rejections'] == b[i]['rejections'] for i in common)
            and offline[method].observations_used == node_result.observations_used
            and offline[method].observations_rejected == node_result.observations_rejected)
        if all('track_id' in r for r in a.values()) and b:
            entry['same_track_ids'] = bool(
                sorted((i, r['track_id']) for i, r in a.items())
                == sorted((i, r.get('track_id')) for i, r in b.items()))
        document[method] = entry
    return document


def fill_node_association(offline, nodes, document):
    """
    Give the through-the-nodes results without IDs their sighting scores.

    The nodes do not publish which track each sighting went to. When a method's two
    maps agree exactly (``agreement``: same track IDs matched to the same landmarks,
    same counts, means within 1e-9 m), the nodes associated every sighting as the
    offline run did, and its ``association_accuracy``, ``oracle_accuracy`` and
    confusion are the nodes' too; otherwise the accuracies stay NaN (JSON null).
    """
    for method, result in nodes.items():
        a, entry = result.association, document.get(method, {})
        if a is None or offline[method].association is None:
            continue
        if (entry.get('same_track_ids') and entry.get('same_counts')
                and entry.get('max_mean_diff_m', 1.0) <= 1e-9):
            source = offline[method].association
            result.association = replace(a, association_accuracy=source.association_accuracy,
                                         oracle_accuracy=source.oracle_accuracy,
                                         confusion=dict(source.confusion))


def format_agreement(document):
    """Return the agreement lines."""
    lines = ['== agreement through the nodes vs offline']
    for method, e in document.items():
        lines.append(f'  {method:<30} same landmarks {"yes" if e["same_ids"] else "NO"}, '
                     f'same counts {"yes" if e["same_counts"] else "NO"}, max |dmean| '
                     f'{e["max_mean_diff_m"]:.2e} m, max |dP| {e["max_cov_diff_m2"]:.2e} m^2, '
                     f'max |dP_dep| {e["max_cov_dep_diff_m2"]:.2e} m^2'
                     + ('' if 'same_track_ids' not in e else
                        f', same track IDs {"yes" if e["same_track_ids"] else "NO"}'))
    return '\n'.join(lines)


def format_node_info(info):
    """Return the timing and per-node counter lines of a run through the nodes."""
    lines = [f'== through the nodes: {info["clouds"]} clouds ({info["rows"]} rows) in '
             f'{info["play_wall_s"]:.1f} s ({info["speedup"]:.1f}x real time), '
             f'{info["wall_s"]:.1f} s in all with {info["startup_s"]:.1f} s start-up; '
             f'{info["barriers"]} barriers ({info["barrier_rounds"]} rounds)']
    keys = ('poses_in', 'observation_messages_in', 'observations_in', 'landmarks_out')
    partial = ('partial_rows', 'partial_out')  # counted once there are partial rows
    for name, values in info['observers'].items():
        problems = {k: v for k, v in values.items() if k not in keys + partial + (
            'pose_buffer_size', 'pending_messages') and v != '0'}
        shown = keys + tuple(k for k in partial if k in values)
        lines.append(f'  observer {name}: ' + ', '.join(f'{k} {values.get(k)}' for k in shown)
                     + (f'; problems {problems}' if problems else ''))
    for method, sources in info['fusers'].items():
        parts = [f'{topic} in {v.get("messages_in")} msgs/{v.get("observations_in")} rows, '
                 f'fused {v.get("fused", 0)}, gated {v.get("gated_out", 0)}'
                 if 'partial_in' not in v else
                 f'{topic} in {v.get("messages_in")} msgs/{v.get("partial_in")} partial, '
                 f'fused {v.get("partial_fused", 0)}, gated {v.get("partial_gated", 0)}, '
                 f'initialised {v.get("landmarks_initialised", 0)}'
                 for topic, v in sources.items()]
        lines.append(f'  fuser {method}: ' + '; '.join(parts))
    cpu = ', '.join(f'{name} {value:.1f}' for name, value in info['cpu_s'].items())
    lines.append(f'  CPU [s]: {cpu}; total {sum(info["cpu_s"].values()):.1f}')
    for method, problem in info['cloud_mismatch'].items():
        lines.append(f'  WARNING {method}: {problem}')
    return '\n'.join(lines)
