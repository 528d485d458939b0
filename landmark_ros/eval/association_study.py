"""
Monte Carlo study of landmarks without IDs: association, tracks, consistency (ROS-free).

``python -m landmark_ros.eval.association_study [--seeds 50] [--table-seeds 10]
[--duration 20] [--json FILE]`` runs the simulator (``landmark_ros.sim.simulation``)
with the landmark IDs hidden, through the pipeline the nodes run
(``eval.montecarlo.fuse_simulation``: one ``Observer`` per robot, the fusers fed every
landmark batch with its classes and scan terms and fused every ``update_period_s`` of
simulated time), several ``fuser.Fuser`` on the same simulated messages.

Track confirmation
------------------
Every fuser runs with the package defaults: a track is confirmed and deleted by its
score, the sequential probability ratio test of ``fuser.track_score`` (``alpha`` =
``false_track_probability``, ``beta`` = ``lost_track_probability``), with the clutter
density, the detection probability and the view estimated from the data per source;
nothing is set for the simulated sensor (``STUDY_SETTING`` is empty). ``independent``
(the default association with ``independent`` fusion) is the reference for consistency.

Consistency. Split CI, the default fusion, takes each robot's pose error as shared;
the simulator draws it independently per observation, so split CI is conservative
here with IDs too (``eval.montecarlo``: average NEES 0.22 in white noise).
``independent`` fusion is the exact model of the simulator: its ANEES must contain 2,
and association errors would push it up; split CI must not be above 2. The headline
case is also run in the ``shared_frame`` scenario of ``eval.montecarlo``
(``FRAME_SCENARIO``: the team's map frame off by one rigid transform per run, no white
pose error), where the dependent parts are what split CI assumes: its ANEES must not be
above 2 there either (split CI bounds each source's dependent part for any correlation,
so it is tight, not exact: frame-averaged about 1.86; ``independent`` fusion is
over-confident there); the frame-averaged ANEES of the matched tracks
(``eval.montecarlo.frame_averaged_nees``) is reported next to it.

World
-----
``pairs`` pairs of landmarks (IDs ``1 .. 2 pairs``): the pair centres apart as the
simulator places landmarks (``generate_world``: about 3 m in the default 20 m world),
the two landmarks of a pair exactly ``spacing`` apart in a random direction, so the
closest landmarks are ``spacing`` apart (as the barcode pairs of MRCLAM). Three robots
(simulator defaults: range noise 0.1 m, bearing 0.02 rad, 8 m range, 2 rad field of
view), each visible landmark detected with probability ``detection_probability``
(0.9) and a Poisson number of clutter rows per message (mean ``clutter_rate``)
uniform in the field of view.

Scores
------
Per seed and fuser, the confirmed tracks are matched one to one to the true landmarks
by optimal assignment on positions (``eval.metrics.match_tracks``) within
``c = min(0.5 m, spacing / 2)``:

precision
    Matched tracks over confirmed tracks.
recall
    Observable true landmarks (detected at least ``min_observations`` times) with a
    matched track, over the observable ones.
duplicates
    Unmatched tracks within ``c`` of a true landmark (a second track on it).
false tracks
    Unmatched tracks farther than ``c`` from every true landmark (confirmed clutter).
association accuracy
    True sightings that went to the track matched to their landmark (merges
    followed), over the true sightings; ``clutter absorbed``: clutter rows that went
    to a matched track, over the clutter rows.
ANEES
    Of the matched tracks against their true landmarks: pooled, with its chi-square
    interval (2 K dof, for reference), and, as in ``eval.montecarlo``, the mean of
    the per-seed averages with its 95 % confidence interval (the seeds are the
    independent samples; the landmarks of one seed share the robots' pose errors).

The headline case (``spacing`` 1 m, p_D 0.9, one clutter row per message) is checked
against the issue's targets for the default association (JCBB): precision >= 99 %,
recall >= 99 %, no duplicates, 2 inside the seed-mean confidence interval. The table
gives every method at every spacing (1, 0.5, 0.25 m) and clutter rate (0, 1, 3).
"""

import argparse
from dataclasses import dataclass, field, replace
import json
import sys
import time
from typing import Dict, List, Optional, Sequence

from landmark_ros.eval.metrics import anees_interval, evaluate, match_tracks
from landmark_ros.eval.montecarlo import frame_averaged_nees, fuse_simulation, SCENARIOS
from landmark_ros.pipeline.config import FuserConfig
from landmark_ros.pipeline.rows import UNKNOWN_ID
from landmark_ros.sim import simulation
from landmark_ros.sim.world import generate_world, rng, World
import numpy as np
from numpy.typing import NDArray

METHODS = ('nearest_neighbour', 'global_nearest_neighbour', 'jcbb')
"""The association methods (``FuserConfig.association``)."""

SHORT = {'nearest_neighbour': 'nn', 'global_nearest_neighbour': 'gnn', 'jcbb': 'jcbb'}

SPACINGS = (1.0, 0.5, 0.25)
"""Distances between the two landmarks of a pair in the table [m]."""

CLUTTER_RATES = (0.0, 1.0, 3.0)
"""Mean clutter rows per message in the table."""

HEADLINE = {'spacing': 1.0, 'clutter_rate': 1.0, 'detection_probability': 0.9}
"""The case the targets are about."""

STUDY_SETTING: Dict[str, object] = {}
"""Changes to the package defaults for the study: none (module docstring)."""

FRAME_SCENARIO = 'shared_frame'
"""The ``eval.montecarlo`` scenario the headline case is also run in."""

TARGETS = {'precision': 0.99, 'recall': 0.99, 'duplicates': 0}
"""The issue's targets for the headline case and the default association."""

_PAIRS_STREAM = 100
"""Stream number of the pair directions (``sim.world.rng``), apart from the simulator's."""


def paired_world(pairs: int, spacing: float, size: float, seed: int) -> World:
    """
    Return ``pairs`` pairs of landmarks ``spacing`` apart, the pairs spread out.

    Parameters
    ----------
    pairs : int
        Number of pairs; the IDs are ``1 .. 2 pairs`` (a pair: ``2k - 1``, ``2k``).
    spacing : float
        Distance between the two landmarks of a pair [m].
    size : float
        Side of the square world, centred on the origin [m].
    seed : int
        Seed of the centres (``generate_world``) and of the directions.

    Returns
    -------
    World

    """
    centres = generate_world(pairs, size, seed)
    angle = rng(seed, _PAIRS_STREAM).uniform(-np.pi, np.pi, pairs)
    half = 0.5 * spacing * np.column_stack([np.cos(angle), np.sin(angle)])
    positions = np.stack([centres.positions - half, centres.positions + half], axis=1)
    return World(np.arange(1, 2 * pairs + 1, dtype=np.int64),
                 positions.reshape(-1, 2), centres.bounds)


@dataclass
class Score:
    """Counts of one fuser over one or more seeds (sums; ``nees`` and ``seed_anees`` lists)."""

    tracks: int = 0
    matched: int = 0
    observable: int = 0
    found: int = 0
    """Observable true landmarks with a matched track."""
    duplicates: int = 0
    false_tracks: int = 0
    sightings: int = 0
    right: int = 0
    clutter_rows: int = 0
    clutter_absorbed: int = 0
    unscored_messages: int = 0
    """Messages whose rows did not all reach the fuser (left out of the accuracy)."""
    nees: List[float] = field(default_factory=list)
    seed_anees: List[float] = field(default_factory=list)
    frame_seed_anees: List[float] = field(default_factory=list)
    """Per seed, with a frame error: the frame-averaged ANEES of the matched tracks
    (``eval.montecarlo.frame_averaged_nees``)."""

    def add(self, other: 'Score') -> None:
        """Add another score's counts to this one."""
        for name in ('tracks', 'matched', 'observable', 'found', 'duplicates',
                     'false_tracks', 'sightings', 'right', 'clutter_rows',
                     'clutter_absorbed', 'unscored_messages'):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        self.nees += other.nees
        self.seed_anees += other.seed_anees
        self.frame_seed_anees += other.frame_seed_anees

    def summary(self) -> Dict[str, object]:
        """Return the rates: precision, recall, accuracy, ANEES and their intervals."""
        anees = float(np.mean(self.nees)) if self.nees else float('nan')
        seeds = len(self.seed_anees)
        mean = float(np.mean(self.seed_anees)) if seeds else float('nan')
        half = (1.96 * float(np.std(self.seed_anees, ddof=1)) / np.sqrt(seeds)
                if seeds > 1 else float('nan'))
        low, high = anees_interval(len(self.nees)) if self.nees else (float('nan'),) * 2
        frame = {}
        if self.frame_seed_anees:
            frame_seeds = len(self.frame_seed_anees)
            frame = {'frame_anees_mean': float(np.mean(self.frame_seed_anees)),
                     'frame_anees_half_width': (
                         1.96 * float(np.std(self.frame_seed_anees, ddof=1))
                         / np.sqrt(frame_seeds) if frame_seeds > 1 else float('nan'))}
        return {
            'precision': self.matched / self.tracks if self.tracks else 1.0,
            'recall': self.found / self.observable if self.observable else 1.0,
            'duplicates': self.duplicates, 'false_tracks': self.false_tracks,
            'tracks': self.tracks, 'observable': self.observable,
            'association_accuracy': self.right / self.sightings if self.sightings else 1.0,
            'clutter_absorbed': (self.clutter_absorbed / self.clutter_rows
                                 if self.clutter_rows else 0.0),
            'anees': anees, 'anees_interval': [low, high],
            'seed_anees_mean': mean, 'seed_anees_half_width': half,
            'seeds': seeds, 'unscored_messages': self.unscored_messages, **frame}


def score_fuser(fuser, measurements: Dict[tuple, NDArray[np.int64]], world: World,
                spacing: float, min_observations: int) -> Score:
    """
    Score one fuser of one seed against the truth.

    Parameters
    ----------
    fuser : fuser.Fuser
        After the run, with its ``association_log``.
    measurements : dict
        ``(robot, stamp_ns) -> true IDs`` of every observation message
        (``fuse_simulation``).
    world : World
        The true landmarks.
    spacing : float
        Closest distance between true landmarks [m]; the match radius is
        ``min(0.5, spacing / 2)``.
    min_observations : int
        Detections that make a true landmark observable.

    Returns
    -------
    Score

    """
    score = Score()
    radius = min(0.5, 0.5 * spacing)
    ids, m, P = fuser.snapshot()[:3]
    match = match_tracks(m, world.positions, radius)
    track_to_true = {int(t): int(world.ids[j]) for t, j in zip(ids.tolist(), match.tolist())
                     if j >= 0}
    detections = np.concatenate(list(measurements.values())) if measurements else (
        np.zeros(0, np.int64))
    counts = np.array([np.count_nonzero(detections == i) for i in world.ids.tolist()])
    observable = counts >= min_observations
    found = np.zeros(len(world.ids), bool)
    found[match[match >= 0]] = True
    score.tracks, score.matched = len(ids), int((match >= 0).sum())
    score.observable, score.found = int(observable.sum()), int((found & observable).sum())
    for k in np.flatnonzero(match < 0).tolist():
        distance = np.min(np.linalg.norm(world.positions - m[k], axis=1))
        if distance <= radius:
            score.duplicates += 1
        else:
            score.false_tracks += 1
    sources = {name: r for r, name in enumerate(fuser.sources)}
    for source, stamp_ns, assigned in fuser.association_log:
        true_ids = measurements.get((sources[source], int(stamp_ns)))
        if true_ids is None or len(true_ids) != len(assigned):
            score.unscored_messages += 1
            continue
        went_to = np.array([track_to_true.get(fuser.tracker.resolve(int(i)), -1)
                            for i in assigned.tolist()], np.int64)
        clutter = true_ids == UNKNOWN_ID
        score.sightings += int((~clutter).sum())
        score.right += int((went_to[~clutter] == true_ids[~clutter]).sum())
        score.clutter_rows += int(clutter.sum())
        score.clutter_absorbed += int((went_to[clutter] >= 0).sum())
    matched = match >= 0
    truth = world.truth()
    results, summary = evaluate(np.array([track_to_true[int(i)] for i in ids[matched]],
                                         np.int64), m[matched], P[matched], truth)
    score.nees = [r.nees for r in results]
    if score.nees:
        score.seed_anees = [float(np.mean(score.nees))]
    return score


def study_configs(methods: Sequence[str] = METHODS,
                  references: bool = False) -> Dict[str, FuserConfig]:
    """
    Return the fusers of the study: ``name -> FuserConfig``.

    One per association method with ``STUDY_SETTING``; with ``references`` also
    ``independent`` (the default association with ``STUDY_SETTING`` and independent
    fusion).
    """
    study = replace(FuserConfig(), **STUDY_SETTING)
    configs = {method: replace(study, association=method) for method in methods}
    if references:
        configs['independent'] = replace(study, fusion='independent')
    return configs


def run_case(spacing: float, clutter_rate: float, seed: int,
             configs: Optional[Dict[str, FuserConfig]] = None,
             detection_probability: float = 0.9, duration_s: float = 20.0,
             pairs: int = 10, scenario: str = 'white') -> Dict[str, Score]:
    """
    Simulate one seed of one case and score every association method on it.

    Parameters
    ----------
    spacing : float
        Distance between the landmarks of a pair [m].
    clutter_rate : float
        Mean clutter rows per message.
    seed : int
        Seed of the world, paths and noise.
    configs : dict of str to FuserConfig, optional
        The fusers, all on the same simulated messages (``study_configs()`` by
        default).
    detection_probability : float
        Probability that a visible landmark is measured.
    duration_s : float
        Simulated time [s].
    pairs : int
        Pairs of landmarks.
    scenario : str
        Key of ``eval.montecarlo.SCENARIOS``: its changes to the simulator defaults.

    Returns
    -------
    dict
        ``name -> Score``.

    Raises
    ------
    RuntimeError
        If an observer rejected a row (the study would not be about what the nodes
        publish).

    """
    sim_config = replace(simulation.SimConfig(), seed=seed, duration_s=duration_s,
                         detection_probability=detection_probability,
                         clutter_rate=clutter_rate, **SCENARIOS[scenario])
    world = paired_world(pairs, spacing, sim_config.world_size, seed)
    sim = simulation.Simulation(sim_config, world)
    configs = study_configs() if configs is None else configs
    measurements: Dict[tuple, NDArray[np.int64]] = {}
    fusers, observers = fuse_simulation(sim, configs=configs, hide_ids=True,
                                        measurements=measurements)
    for robot, observer in enumerate(observers):
        status = observer.status()
        if status.level != 'ok':
            raise RuntimeError(f'observer of robot{robot + 1}: {status.message}')
    scores = {name: score_fuser(fuser, measurements, world, spacing,
                                configs[name].min_observations)
              for name, fuser in fusers.items()}
    if sim.frame_error is not None:
        for name, fuser in fusers.items():
            ids, m, P = fuser.snapshot()[:3]
            match = match_tracks(m, world.positions, min(0.5, 0.5 * spacing))
            if (match >= 0).any():
                scores[name].frame_seed_anees = [float(np.mean(frame_averaged_nees(
                    sim, world.ids[match[match >= 0]], m[match >= 0], P[match >= 0])))]
    return scores


def frame_configs(method: str = FuserConfig().association) -> Dict[str, FuserConfig]:
    """
    Return the fusers of the headline case in ``FRAME_SCENARIO``: ``name -> FuserConfig``.

    The association ``method`` with ``STUDY_SETTING`` and each fusion method: split CI
    (the default, under the method's name), ``independent`` and
    ``covariance_intersection``.
    """
    study = replace(FuserConfig(), **STUDY_SETTING, association=method)
    return {method: study, 'independent': replace(study, fusion='independent'),
            'covariance_intersection': replace(study, fusion='covariance_intersection')}


def run(seeds: int = 50, table_seeds: int = 10, duration_s: float = 20.0,
        spacings: Sequence[float] = SPACINGS, clutter_rates: Sequence[float] = CLUTTER_RATES,
        methods: Sequence[str] = METHODS, frame: bool = True,
        out=sys.stdout) -> Dict[str, object]:
    """
    Run the headline case and the table; print them.

    Parameters
    ----------
    seeds : int
        Seeds of the headline case (0 to ``seeds - 1``).
    table_seeds : int
        Seeds per table cell (the first ``table_seeds`` of the same seeds; the
        headline cell reuses its first ones).
    duration_s : float
        Simulated time per seed [s].
    spacings, clutter_rates : sequence of float
        The table's rows.
    methods : sequence of str
        Association methods.
    frame : bool
        Also run the headline case in ``FRAME_SCENARIO`` (``frame_configs``, the
        same seeds).
    out : file
        Where the tables go.

    Returns
    -------
    dict
        ``headline``: ``method -> Score.summary()`` plus ``targets_met`` (default
        method); ``table``: list of ``{spacing, clutter_rate, method, **summary}``;
        with ``frame``, ``frame_headline``: ``name -> Score.summary()``.

    """
    cells: Dict[tuple, Dict[str, Score]] = {}

    headline_key = (HEADLINE['spacing'], HEADLINE['clutter_rate'])

    def cell(spacing, clutter_rate, count, scenario='white'):
        key = (spacing, clutter_rate, scenario)
        configs = (frame_configs() if scenario == FRAME_SCENARIO else
                   study_configs(methods, references=key[:2] == headline_key))
        scores = cells.setdefault(key, {'_seeds': 0, **{m: Score() for m in configs}})
        for seed in range(scores['_seeds'], count):
            for name, score in run_case(spacing, clutter_rate, seed, configs,
                                        HEADLINE['detection_probability'],
                                        duration_s, scenario=scenario).items():
                scores[name].add(score)
            scores['_seeds'] = max(scores['_seeds'], seed + 1)
        return scores

    table = []
    print(f"{'spacing':>7} {'clutter':>7} {'method':<11} {'precision':>9} {'recall':>7} "
          f"{'dup':>4} {'false':>5} {'accuracy':>8} {'absorbed':>8} {'ANEES':>6} "
          f"{'seed mean 95 %':>20}", file=out)
    for spacing in spacings:
        for clutter_rate in clutter_rates:
            scores = cell(spacing, clutter_rate, table_seeds)
            for method in methods:
                s = scores[method].summary()
                table.append({'spacing': spacing, 'clutter_rate': clutter_rate,
                              'method': method, 'seeds': table_seeds, **s})
                print(_line(spacing, clutter_rate, method, s), file=out)
    headline = cell(*headline_key, seeds)
    default = FuserConfig().association
    names = [name for name in headline if name != '_seeds']
    result = {'headline': {name: headline[name].summary() for name in names},
              'table': table, 'study_setting': dict(STUDY_SETTING), 'seeds': seeds,
              'table_seeds': table_seeds, 'duration_s': duration_s}
    s = result['headline'][default]
    low, high = _seed_interval(s)
    reference = result['headline']['independent']
    ref_low, ref_high = _seed_interval(reference)
    met = {'precision': s['precision'] >= TARGETS['precision'],
           'recall': s['recall'] >= TARGETS['recall'],
           'duplicates': s['duplicates'] <= TARGETS['duplicates'],
           'anees split CI not above 2': bool(low <= 2.0),
           'anees independent contains 2': bool(ref_low <= 2.0 <= ref_high)}
    if frame:
        framed = cell(*headline_key, seeds, FRAME_SCENARIO)
        result['frame_headline'] = {name: framed[name].summary()
                                    for name in framed if name != '_seeds'}
        frame_low, _ = _seed_interval(result['frame_headline'][default])
        met[f'anees split CI not above 2 ({FRAME_SCENARIO})'] = bool(frame_low <= 2.0)
    result['targets_met'] = met
    print(f"\nheadline: spacing {HEADLINE['spacing']} m, p_D "
          f"{HEADLINE['detection_probability']}, {HEADLINE['clutter_rate']:g} clutter row "
          f'per message, {seeds} seeds x {duration_s:g} s; {default} = the study setting '
          f'{STUDY_SETTING}', file=out)
    for name in names:
        print(_line(HEADLINE['spacing'], HEADLINE['clutter_rate'], name,
                    result['headline'][name]), file=out)
    if frame:
        print(f'headline in scenario {FRAME_SCENARIO} ({default}, study setting; the '
              'fusion methods):', file=out)
        for name, summary in result['frame_headline'].items():
            mean, half = summary['frame_anees_mean'], summary['frame_anees_half_width']
            print(_line(HEADLINE['spacing'], HEADLINE['clutter_rate'], name, summary)
                  + f'  frame-averaged {mean:5.2f} [{mean - half:5.2f}, {mean + half:5.2f}]',
                  file=out)
    print(f'targets ({default}, study setting): ' + ', '.join(
        f"{name} {'met' if ok else 'NOT met'}" for name, ok in met.items()), file=out)
    return result


def _seed_interval(summary):
    mean, half = summary['seed_anees_mean'], summary['seed_anees_half_width']
    return mean - half, mean + half


def _line(spacing, clutter_rate, method, s):
    low, high = _seed_interval(s)
    return (f'{spacing:7.2f} {clutter_rate:7.1f} {SHORT.get(method, method):<11} '
            f"{100 * s['precision']:8.2f}% {100 * s['recall']:6.2f}% {s['duplicates']:4d} "
            f"{s['false_tracks']:5d} {100 * s['association_accuracy']:7.2f}% "
            f"{100 * s['clutter_absorbed']:7.2f}% {s['anees']:6.2f} "
            f"{s['seed_anees_mean']:6.2f} [{low:5.2f}, {high:5.2f}]")


def main(argv=None) -> int:
    """Run the study from the command line; exit 1 if a headline target is missed."""
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--seeds', type=int, default=50, help='seeds of the headline case')
    parser.add_argument('--table-seeds', type=int, default=10, help='seeds per table cell')
    parser.add_argument('--duration', type=float, default=20.0,
                        help='simulated seconds per seed')
    parser.add_argument('--json', default=None, help='write the results as JSON')
    parser.add_argument('--no-frame', action='store_true',
                        help=f'skip the headline case in scenario {FRAME_SCENARIO}')
    args = parser.parse_args(argv)
    if args.seeds < 2 or args.table_seeds < 1 or args.duration <= 0.0:
        parser.error('--seeds must be >= 2, --table-seeds >= 1, --duration > 0')
    started = time.monotonic()
    result = run(args.seeds, min(args.table_seeds, args.seeds), args.duration,
                 frame=not args.no_frame)
    elapsed = time.monotonic() - started
    print(f'{elapsed:.1f} s')
    if args.json:
        with open(args.json, 'w') as stream:
            json.dump(dict(result, elapsed_s=elapsed), stream, indent=1,
                      default=lambda value: None)
    return 0 if all(result['targets_met'].values()) else 1


if __name__ == '__main__':
    sys.exit(main())
