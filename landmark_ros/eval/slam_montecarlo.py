"""
Monte Carlo of the team without motion capture: pose NEES and map ANEES over seeds.

Each seed draws a world (``sim.world.generate_world``: 15 landmarks in 20 m), one loop
path per robot at 0.5 m/s (``sim.world.make_paths``), wheel odometry at ``rate_hz``
with the odometry model's noise (``sim.odometry.wheel_odometry``), range-bearing
sightings of the landmarks in view (``sim.world.visible``: up to 8 m, all around)
and of the other robots every 0.4 s with white noise, and starting poses drawn from
their stated covariance. The team runs the closed loop of ``eval.slam_loop.TeamLoop``
(the localizer, observer and fuser of the nodes, package defaults: split CI in the
localizer and in the fuser) with the same models (exact up to the linearisation).

Figures (Bar-Shalom, Li and Kirubarajan 2001, ch. 5.4):

- pose: per seed the average NEES of the 3-dof poses of every robot over the run (after
  the first 2 s); over the seeds their mean with its 95 % interval (normal
  approximation of the seed means), and the fraction of the odometry stamps at which
  the NEES averaged over seeds and robots lies inside its chi-square interval
  (3 dof times seeds times robots);
- map: the NEES of every confirmed landmark at the end of each seed, averaged over
  seeds and landmarks, against the chi-square interval of that many 2-dof estimates;
  and where its error lies: the RMSE left after the best rigid transform of each seed's
  map onto the truth (``eval.slam_attribution.rigid_fit``), beside the RMSE its
  covariances predict (square root of the mean trace).

Consistent: 3 inside the pose interval, the map ANEES inside its interval (with
``--estimator team_ekf``, whose map has a joint covariance, its joint NEES per degree
of freedom: the landmarks share the frame's error, which the per-landmark interval
takes as independent).
Run: ``python -m landmark_ros.eval.slam_montecarlo [--seeds 20] [--duration 60]
[--precision-sources K]``; ``--long`` adds the 10-minute run (fewer seeds). Variants of
the loop (``Variant``): ``--initial-stddev X Y YAW`` (the starting poses' error and its
stated standard deviations), ``--source-correlation`` (the fuser's) and
``--landmark-correlation`` (the localizers').
"""

import argparse
from dataclasses import dataclass
import math
import sys

from landmark_ros.core.gating import mahalanobis_sq
from landmark_ros.eval.metrics import anees_interval, chi2_quantile
from landmark_ros.eval.slam_attribution import rigid_fit
from landmark_ros.eval.slam_loop import LoopConfig, TeamLoop
from landmark_ros.eval.team_ekf import TeamEKF
from landmark_ros.fusion.methods import SOURCE_CORRELATIONS
from landmark_ros.localizer import motion
from landmark_ros.localizer.config import LANDMARK_CORRELATIONS, LocalizerConfig
from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
from landmark_ros.sim.odometry import wheel_odometry
from landmark_ros.sim.world import generate_world, make_paths, visible
import numpy as np

ALPHAS = (0.05, 0.5, 0.05, 0.01)
RANGE_STDDEV, BEARING_STDDEV = 0.05, 0.02
INITIAL_STDDEV = (0.05, 0.05, 0.02)
MAX_RANGE, FOV = 8.0, 2.0 * math.pi
ESTIMATORS = {'loop': TeamLoop, 'team_ekf': TeamEKF}
"""What ``Variant.estimator`` names."""


@dataclass(frozen=True)
class SeedResult:
    """What one seed gives."""

    nees: np.ndarray
    """Pose NEES per odometry stamp (after 2 s), averaged over the robots, shape (K,)."""
    map_nees: np.ndarray
    """NEES of every confirmed landmark at the end, shape (L,)."""
    map_errors: np.ndarray
    """Their position errors [m], shape (L,)."""
    position_errors: np.ndarray
    """Position errors of every robot at every stamp after 2 s [m], shape (K * robots,)."""
    map_residuals: np.ndarray
    """Distances left after the best rigid transform of the map onto the truth [m], (L,)."""
    map_traces: np.ndarray
    """Traces of the landmarks' covariances [m^2], shape (L,)."""
    map_joint_nees: float = math.nan
    """NEES of all landmarks at once with their joint covariance (``team_ekf`` only)."""


@dataclass(frozen=True)
class Variant:
    """What a study changes in the loop (the defaults: the package's loop)."""

    precision_sources: int = 1
    """Sources per robot in the fuser (the observers' ``precision_sources``)."""
    initial_stddev: tuple = INITIAL_STDDEV
    """Standard deviations of the starting poses' error, drawn and stated [m, m, rad]."""
    source_correlation: str = 'unknown'
    """The fuser's ``source_correlation``."""
    landmark_correlation: str = 'independent'
    """The localizers' ``landmark_correlation``."""
    estimator: str = 'loop'
    """``loop`` (``TeamLoop``, the nodes' pipeline) or ``team_ekf`` (``eval.team_ekf``,
    the reference that keeps every correlation)."""


def loop_config(variant=None):
    """Return the loop's parameters: package defaults with the simulation's models."""
    variant = variant or Variant()
    localizer = LocalizerConfig(odometry_alphas=ALPHAS, range_stddev=RANGE_STDDEV,
                                range_stddev_per_m=0.0, bearing_stddev=BEARING_STDDEV,
                                initial_stddev=tuple(variant.initial_stddev),
                                landmark_correlation=variant.landmark_correlation)
    observer = ObserverConfig(range_stddev=RANGE_STDDEV, range_stddev_per_m=0.0,
                              bearing_stddev=BEARING_STDDEV,
                              precision_sources=variant.precision_sources)
    # Change detection off, as in every loop (mrclam.slam.loop_config): the rows carry
    # the localizers' slow pose errors, not the white rows its test takes.
    fuser = FuserConfig(move_false_alarm_rate=0.0,
                        source_correlation=variant.source_correlation)
    return LoopConfig(localizer, observer, fuser)


def _sightings(generator, pose, positions):
    """Return which of ``positions`` a robot at ``pose`` sees, and noisy observations."""
    mask, z = visible(pose, positions, 0.5, MAX_RANGE, FOV)
    z = z[mask] + generator.normal(0.0, [RANGE_STDDEV, BEARING_STDDEV], (int(mask.sum()), 2))
    return mask, z


def run_seed(seed, robots=3, duration_s=60.0, rate_hz=20.0, variant=None):
    """Run one seed of the closed loop (``variant``: None, the package's); its ``SeedResult``."""
    variant = variant or Variant()
    generator = np.random.default_rng(seed)
    world = generate_world(15, 20.0, seed)
    paths = make_paths(robots, world.bounds, 0.5, seed)
    times = np.arange(0.0, duration_s, 1.0 / rate_hz)
    truth = [np.array(path.pose(times)).reshape(-1, 3) for path in paths]
    odom = [wheel_odometry(t, ALPHAS, generator) for t in truth]
    names = [f'robot{i + 1}' for i in range(robots)]
    loop = ESTIMATORS[variant.estimator](loop_config(variant=variant), names)
    P0 = np.diag(np.square(variant.initial_stddev))
    for i in range(robots):
        loop.start(i, 1, truth[i][0] + generator.multivariate_normal(np.zeros(3), P0), P0)
    every = int(round(0.4 * rate_hz))
    nees, errors = [], []
    for k, t in enumerate(times):
        stamp = int(round(t * 1e9)) + 2
        for i in range(robots):
            loop.odometry(i, stamp, pose=odom[i][k])
        if k % every == every // 2:
            for i in range(robots):
                mask, z = _sightings(generator, truth[i][k], world.positions)
                loop.sightings(i, stamp + 1000, world.ids[mask], z)
                others = [j for j in range(robots) if j != i]
                mask, z = _sightings(generator, truth[i][k],
                                     np.array([truth[j][k, :2] for j in others]))
                for j, z_j in zip(np.array(others)[mask].tolist(), z):
                    loop.robot_sighting(i, stamp, j, z_j)
        if t >= 2.0:
            step_nees = []
            for i in range(robots):
                est = loop.estimate(i)
                e = est.x - truth[i][k]
                e[2] = motion.wrap(e[2])
                step_nees.append(float(e @ np.linalg.solve(est.P, e)))
                errors.append(math.hypot(e[0], e[1]))
            nees.append(np.mean(step_nees))
    snapshot = loop.map_snapshot()
    truth_m = world.positions[np.searchsorted(world.ids, snapshot.ids)]
    map_nees = np.array([float(mahalanobis_sq(truth_m[k], snapshot.m[k], snapshot.P[k]))
                         for k in range(len(snapshot.ids))])
    map_errors = np.linalg.norm(snapshot.m - truth_m, axis=1)
    fit = rigid_fit(snapshot.m, truth_m, truth_m.mean(axis=0)) if len(truth_m) else None
    return SeedResult(np.array(nees), map_nees, map_errors, np.array(errors),
                      np.linalg.norm(fit.residual, axis=1) if fit else np.empty(0),
                      np.trace(snapshot.P, axis1=1, axis2=2), _joint_nees(loop, world))


def _joint_nees(loop, world):
    """Return the map's NEES with its joint covariance (NaN without one)."""
    if not hasattr(loop, 'joint_map'):
        return math.nan
    ids, m, P = loop.joint_map()
    e = (m - world.positions[np.searchsorted(world.ids, ids)]).reshape(-1)
    return float(e @ np.linalg.solve(P, e)) if len(e) else math.nan


def summarise(results, robots):
    """Return the figures of a list of ``SeedResult`` (module docstring) as a dict."""
    means = np.array([r.nees.mean() for r in results])
    half = 1.96 * means.std(ddof=1) / math.sqrt(len(means)) if len(means) > 1 else math.inf
    count = min(len(r.nees) for r in results)
    per_stamp = np.mean([r.nees[:count] for r in results], axis=0)
    n = len(results) * robots
    low, high = chi2_quantile(3 * n, 0.025) / n, chi2_quantile(3 * n, 0.975) / n
    inside = float(np.mean((per_stamp >= low) & (per_stamp <= high)))
    map_nees = np.concatenate([r.map_nees for r in results])
    map_low, map_high = anees_interval(len(map_nees))
    errors = np.concatenate([r.position_errors for r in results])
    return {'seeds': len(results), 'pose_anees': float(means.mean()),
            'pose_anees_interval': [float(means.mean() - half), float(means.mean() + half)],
            'pose_stamps_inside_fraction': inside,
            'pose_stamp_interval': [float(low), float(high)],
            'position_rmse_m': _rms(errors),
            'map_anees': float(map_nees.mean()),
            'map_anees_interval': [float(map_low), float(map_high)],
            'map_rmse_m': _rms(np.concatenate([r.map_errors for r in results])),
            'map_rigid_residual_rmse_m': _rms(np.concatenate([r.map_residuals
                                                              for r in results])),
            'map_predicted_rmse_m': float(math.sqrt(np.mean(np.concatenate(
                [r.map_traces for r in results])))),
            'landmarks_scored': int(len(map_nees)),
            **_joint_summary(results)}


def _joint_summary(results):
    """Return the joint map NEES per degree of freedom over seeds and its interval."""
    joint = np.array([r.map_joint_nees for r in results])
    if not np.all(np.isfinite(joint)):
        return {}
    dof = int(sum(2 * len(r.map_nees) for r in results))
    return {'map_joint_anees': float(joint.sum() / dof),
            'map_joint_anees_interval': [chi2_quantile(dof, 0.025) / dof,
                                         chi2_quantile(dof, 0.975) / dof]}


def _rms(values):
    """Return the root mean square of ``values`` (NaN when empty)."""
    return float(math.sqrt(np.mean(np.square(values)))) if len(values) else math.nan


def consistent(summary):
    """
    Return whether 3 lies in the pose interval and the map's NEES in its interval.

    The map's joint NEES per degree of freedom when the estimator has a joint covariance
    (``team_ekf``), else the landmarks' ANEES.
    """
    low, high = summary['pose_anees_interval']
    key = 'map_joint_anees' if 'map_joint_anees' in summary else 'map_anees'
    map_low, map_high = summary[f'{key}_interval']
    return low <= 3.0 <= high and map_low <= summary[key] <= map_high


def format_summary(name, s):
    """Return one line per figure."""
    low, high = s['pose_anees_interval']
    map_low, map_high = s['map_anees_interval']
    return (f'{name}: {s["seeds"]} seeds; pose ANEES {s["pose_anees"]:.2f} (95 % interval '
            f'{low:.2f} to {high:.2f}; consistent if it holds 3), stamps inside the chi-square '
            f'interval {s["pose_stamps_inside_fraction"]:.3f}, position RMSE '
            f'{s["position_rmse_m"]:.3f} m; map ANEES {s["map_anees"]:.2f} (interval '
            f'{map_low:.2f} to {map_high:.2f}, {s["landmarks_scored"]} landmarks), map RMSE '
            f'{s["map_rmse_m"]:.3f} m ({s["map_rigid_residual_rmse_m"]:.3f} m after a rigid '
            f'transform, {s["map_predicted_rmse_m"]:.3f} m predicted); '
            + (f'joint map NEES per dof {s["map_joint_anees"]:.2f} (interval '
               f'{s["map_joint_anees_interval"][0]:.2f} to '
               f'{s["map_joint_anees_interval"][1]:.2f}); ' if 'map_joint_anees' in s else '')
            + f'{"consistent" if consistent(s) else "NOT consistent"}'
            + (' (map judged by its joint NEES)' if 'map_joint_anees' in s else ''))


def main(argv=None):
    """Print the Monte Carlo figures; exit 1 when a run is not consistent."""
    parser = argparse.ArgumentParser(
        prog='python -m landmark_ros.eval.slam_montecarlo',
        description=__doc__.splitlines()[1] + ' Exits 1 when a run is not consistent.',
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument('--seeds', type=int, default=20, help='seeds of the short run '
                        '(0: none)')
    parser.add_argument('--robots', type=int, default=3, help='robots per seed')
    parser.add_argument('--duration', type=float, default=60.0, help='[s] per seed')
    parser.add_argument('--long', action='store_true',
                        help='add a 600 s run over --long-seeds seeds')
    parser.add_argument('--long-seeds', type=int, default=2, help='seeds of the long run')
    parser.add_argument('--first-seed', type=int, default=0, help='the first seed')
    parser.add_argument('--precision-sources', type=int, default=1,
                        help="sources per robot in the fuser: the observers' "
                        'precision_sources (observer.precision)')
    parser.add_argument('--initial-stddev', type=float, nargs=3, default=INITIAL_STDDEV,
                        metavar=('X', 'Y', 'YAW'),
                        help="the starting poses' error, drawn and stated [m, m, rad]")
    parser.add_argument('--source-correlation', default='unknown',
                        choices=SOURCE_CORRELATIONS, help="the fuser's source_correlation")
    parser.add_argument('--landmark-correlation', default='independent',
                        choices=LANDMARK_CORRELATIONS,
                        help="the localizers' landmark_correlation")
    parser.add_argument('--estimator', default='loop', choices=tuple(ESTIMATORS),
                        help='loop: the pipeline of the nodes; team_ekf: one EKF keeping every '
                        'correlation (eval.team_ekf), the reference')
    args = parser.parse_args(argv)
    variant = Variant(args.precision_sources, tuple(args.initial_stddev),
                      args.source_correlation, args.landmark_correlation, args.estimator)
    runs = [('short', args.seeds, args.duration)] if args.seeds > 0 else []
    if args.long:
        runs.append(('long', args.long_seeds, 600.0))
    ok = True
    for name, seeds, duration in runs:
        results = [run_seed(seed, args.robots, duration, variant=variant)
                   for seed in range(args.first_seed, args.first_seed + seeds)]
        summary = summarise(results, args.robots)
        print(format_summary(f'{name} ({duration:.0f} s)', summary))
        ok = ok and consistent(summary)
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
