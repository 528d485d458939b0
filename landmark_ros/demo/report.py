"""
The demo's evaluation: fused landmarks against the ground truth, the plot.

``evaluate_run`` turns what the ``Monitor`` saw into per-landmark results and a
summary (``eval.metrics``); with ``--no-ids`` it first matches the fused tracks to the
true landmarks (``match_tracks_to_truth``). ``plot_run`` draws the run.
"""

import math

from landmark_ros.eval.metrics import evaluate
from landmark_ros.fuser import map_file

NEES_2SIGMA = 4.0
"""A 2D estimate whose truth lies outside its 2-sigma ellipse has NEES above 4."""
MIN_OBSERVATIONS_NO_IDS = 2
"""The fuser's ``min_observations`` with ``--no-ids``: a track needs a second row."""
SIGHTINGS_TO_CONFIRM_NO_IDS = 5
"""Sightings after which a landmark must be in the map without IDs.

The track score (``fuser.track_score``) confirms a clean track after two to four
rows with its prior clutter and detection estimates; five leaves a margin for the
misses scored while the landmark is in view and not sighted. Landmarks sighted
fewer times may be confirmed already and are then matched like the others.
"""


def rejections_by_id(path, frame):
    """Return ``id -> rejections`` from the fuser's saved map ({} if unreadable)."""
    try:
        document = map_file.load(str(path), frame)
    except (OSError, ValueError):
        return {}
    return {int(r['id']): int(r.get('rejections', 0)) for r in document['landmarks']}


def plot_run(path, monitor, results, seen_ids, unfused_ids, title):
    """
    Draw paths, final poses, true landmarks and the fused estimates.

    The fused estimates are drawn at their true landmark with the error and the
    2-sigma ellipse magnified by one common factor (centimetres on a map of
    metres), so whether the truth lies inside the ellipse reads off directly.
    """
    from landmark_ros.eval import plotting
    import numpy as np
    truth = monitor.truth
    points = np.vstack([truth.m] + [np.array(p).reshape(-1, 3)[:, :2]
                                    for p in monitor.true_paths])
    width, height = np.ptp(points, axis=0) + 1.0
    # Equal axes with 20 % more height on top for the legend: size the figure to fit.
    fig, ax = plotting.new_figure((8.0, float(np.clip(6.8 * 1.2 * height / width + 1.5,
                                                      4.0, 12.0))))
    colours = ['tab:blue', 'tab:green', 'tab:purple', 'tab:brown', 'tab:pink', 'tab:cyan',
               'tab:olive', 'tab:gray']
    for i in range(monitor.robots):
        colour = colours[i % len(colours)]
        path_xy = np.array(monitor.true_paths[i]).reshape(-1, 3)
        if len(path_xy):
            ax.plot(path_xy[:, 0], path_xy[:, 1], color=colour, linewidth=1.0, alpha=0.7)
        if monitor.reported[i] is not None:
            pose, P_pose = monitor.reported[i]
            plotting.draw_robot(ax, pose, P_pose, size=0.8, colour=colour,
                                label=f'robot{i + 1} (path, final pose, 2σ)', sigma=2.0)
    seen = np.isin(truth.ids, list(seen_ids))
    ax.scatter(truth.m[seen, 0], truth.m[seen, 1], marker='+', color='black', s=60,
               label='true landmarks', zorder=3)
    if (~seen).any():
        ax.scatter(truth.m[~seen, 0], truth.m[~seen, 1], marker='+', color='silver', s=60,
                   label='never measured', zorder=3)
    for landmark_id, m in zip(truth.ids.tolist(), truth.m):
        ax.annotate(str(landmark_id), m, textcoords='offset points', xytext=(4, 4),
                    fontsize=7)
    true_by_id = {int(i): m for i, m in zip(truth.ids.tolist(), truth.m)}
    if results:
        sizes = [2.0 * math.sqrt(max(np.linalg.eigvalsh(r.P)[-1], 1e-12)) for r in results]
        scale = max(1.0, round(0.35 / float(np.median(sizes))))
        label = f'fused, 2σ ellipse (error and ellipse ×{scale:g})'
        for r in results:
            true = true_by_id[r.id]
            shown = true + scale * (r.m - true)
            plotting.draw_ellipse(ax, shown, scale ** 2 * r.P, sigma=2.0, color='tab:orange',
                                  linewidth=1.2, label=label)
            ax.plot(*shown, marker='.', color='tab:orange')
            label = None
        outliers = [r for r in results if r.nees > NEES_2SIGMA]
        if outliers:
            xy = np.array([true_by_id[r.id] for r in outliers])
            ax.scatter(xy[:, 0], xy[:, 1], s=260, facecolors='none', edgecolors='red',
                       linewidths=1.5, label='truth outside 2σ', zorder=4)
    if unfused_ids:
        xy = np.array([true_by_id[i] for i in unfused_ids])
        ax.scatter(xy[:, 0], xy[:, 1], marker='x', s=80, color='red',
                   label='measured, not fused', zorder=4)
    # Room above the map for the legend.
    (x_low, y_low), (_, y_high) = ax.dataLim.get_points()
    ax.update_datalim([(x_low, y_high + 0.2 * (y_high - y_low))])
    ax.autoscale_view()
    plotting.finish(fig, ax, path, title)


def evaluate_run(monitor, rejections, no_ids=False):
    """
    Return the per-landmark results, summary, seen and unfused IDs, and the association.

    With ``no_ids`` the fused tracks are first matched to the true landmarks
    (``match_tracks_to_truth``) and take their IDs; the last value is then that
    dict, else None.
    """
    import numpy as np
    truth = monitor.truth
    needed = SIGHTINGS_TO_CONFIRM_NO_IDS if no_ids else 1
    seen = [int(i) for i, n in zip(truth.ids.tolist(), truth.observations.tolist())
            if n >= needed]
    fused = monitor.fused
    association = None
    truth_xy = {int(i): tuple(m) for i, m in zip(truth.ids.tolist(), truth.m)}
    if fused is None:
        fused_ids = np.empty(0, np.int64)
        results, summary = evaluate(fused_ids, np.empty((0, 2)), np.empty((0, 2, 2)), {})
    else:
        fused_ids = fused.ids
        rejected = [rejections.get(int(i), 0) for i in fused.ids.tolist()]
        if no_ids:
            association = match_tracks_to_truth(fused, truth)
            fused_ids = np.array([association['track_to_true'].get(int(i), -1)
                                  for i in fused.ids.tolist()], np.int64)
        results, summary = evaluate(fused_ids, fused.m, fused.P, truth_xy, fused.observations,
                                    rejected)
    unfused = sorted(set(seen) - set(fused_ids.tolist()))
    return results, summary, seen, unfused, association


def match_tracks_to_truth(fused, truth):
    """
    Match tracks found without IDs to the true landmarks (``--no-ids``).

    Parameters
    ----------
    fused : landmark_ros.ros.schemas.LandmarkCloud
        The fused map (``ids``, ``m``, ``observations``).
    truth : landmark_ros.ros.schemas.LandmarkCloud
        The simulator's ground truth (``ids``, ``m``, ``observations``: sightings).

    Returns
    -------
    dict
        ``track_to_true`` (track ID -> true ID, optimal assignment on positions
        within 1 m), ``tracks``, ``extra_tracks`` (matched to nothing), ``gospa_m``
        (c = 1 m, p = 2, alpha = 2), ``observations_matched`` (share of the sightings
        held by the matched tracks: sum of min(track, true) over the matches over
        all sightings; an upper bound of the association accuracy).

    """
    import numpy as np
    from landmark_ros.eval.metrics import evaluate_association
    seen = truth.observations > 0
    truth_xy = {int(i): tuple(m) for i, m, s in zip(truth.ids.tolist(), truth.m, seen) if s}
    summary = evaluate_association(np.zeros(0, np.int64), np.zeros(0, np.int64),
                                   np.zeros((0, 2)), np.zeros((0, 2, 2)), fused.ids,
                                   fused.m, truth_xy)
    sightings = dict(zip(truth.ids.tolist(), truth.observations.tolist()))
    held = sum(min(int(n), int(sightings[summary.track_to_true[int(i)]]))
               for i, n in zip(fused.ids.tolist(), fused.observations.tolist())
               if int(i) in summary.track_to_true)
    total = int(truth.observations.sum())
    return {'track_to_true': summary.track_to_true, 'tracks': len(fused.ids),
            'extra_tracks': len(fused.ids) - len(summary.track_to_true),
            'gospa_m': summary.gospa_m,
            'observations_matched': held / total if total else 1.0}
