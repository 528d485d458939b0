"""
The team without motion capture: localizers, observers and one fuser in a closed loop.

ROS-free; the MRCLAM replay (``landmark_mrclam --slam``) and the Monte Carlo study
(``eval.slam_montecarlo``) drive this one object, and it only composes the pipeline
objects the nodes run: per robot a ``localizer.Localizer`` and an
``observer.Observer``, for the team one ``fuser.Fuser``. The wiring is the one of
``team.launch.py localize:=true``:

- odometry goes to the robot's localizer; each pose it gives (one per odometry
  message, as the node publishes ``pose``) goes to the robot's observer;
- a sighting message goes to the observer, which places its rows in the world with the
  pose interpolated at its stamp; the pose covariance is the rows' dependent part;
- each placed batch goes to the fuser (source ``/robotN/landmarks``) and is fused at
  once (``fuse_queued``);
- the same sightings update the localizer against the fused map as it was before
  that batch was fused (the map never holds the sighting that updates the pose);
  without IDs the rows take the track IDs the fuser's association gave them
  (``LoopConfig.association``; ``localizer``: the localizer associates them itself);
- a sighting of another robot updates the localizer with the other's estimate at that
  stamp (``Localizer.add_robot_sighting``).

Why the loop stays consistent (docs/slam.md, "The team without motion
capture"): every pose the observer uses is the localizer's estimate *before* the
sightings it places (the observer waits for the pose after their stamp, and the loop
hands the sightings to the localizer only after the observer has placed them), so a
row's sensor noise is independent of its pose and of the map; the pose error, which
depends on the map and on this robot's earlier rows, is the row's dependent part, which
the fuser's split CI fuses for any correlation (conservatively inside a source); the
localizer's update treats the map term and its own prior as of unknown correlation
(split CI, ``localizer.update``) and the other robots' estimates likewise.
"""

from dataclasses import dataclass, field
import itertools
from typing import Dict, List, Optional, Sequence, Tuple

from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.localizer import Estimate, Localizer, UNKNOWN_ID
from landmark_ros.observer.observer import LandmarkBatch, ObservationMessage, Observer
from landmark_ros.observer.precision import dependent_stddev, precision_level, precision_topics
from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class LoopConfig:
    """The parameters of every pipeline object of the loop."""

    localizer: LocalizerConfig
    observer: ObserverConfig
    fuser: FuserConfig
    hide_ids: bool = False
    """Send the sightings without IDs: the fuser's association names the landmarks."""
    association: str = 'fuser'
    """With ``hide_ids``, who names the rows for the localizer: ``localizer`` (its own
    association in the robot frame, the pose covariance included, against the map it
    holds, ``localizer.association``) or ``fuser`` (the track IDs the fuser's
    association gave the rows)."""


@dataclass
class PoseTrack:
    """One robot's estimates at its odometry stamps (after the sightings there)."""

    stamps_ns: List[int] = field(default_factory=list)
    x: List[NDArray[np.float64]] = field(default_factory=list)
    P: List[NDArray[np.float64]] = field(default_factory=list)

    def append(self, est: Estimate) -> None:
        """Record one estimate."""
        self.stamps_ns.append(est.stamp_ns)
        self.x.append(est.x)
        self.P.append(est.P)

    def arrays(self) -> Tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """Return stamps (K,) [ns], poses (K, 3) and covariances (K, 3, 3)."""
        return (np.array(self.stamps_ns, np.int64), np.array(self.x).reshape(-1, 3),
                np.array(self.P).reshape(-1, 3, 3))


class TeamLoop:
    """
    Localize a team and build its map at once, from odometry and sightings only.

    Parameters
    ----------
    config : LoopConfig
    names : sequence of str
        Robot names (``robot1``...): sources ``/NAME/landmarks`` of the fuser.

    """

    def __init__(self, config: LoopConfig, names: Sequence[str]) -> None:
        self.config = config
        self.names = list(names)
        self.localizers = [Localizer(config.localizer) for _ in names]
        self.observers = [Observer(config.observer) for _ in names]
        self.sources = [precision_topics(f'/{name}/landmarks',
                                         config.observer.precision_sources)
                        for name in names]
        self.fuser = Fuser(config.fuser, [s for robot in self.sources for s in robot])
        self.fuser.load()
        self.fuser.association_log = [] if config.hide_ids else None
        self.tracks = [PoseTrack() for _ in names]
        # dependent_stddev of every placed message with rows, in order [m]
        self.dependent_stddevs: List[float] = []
        self.counts: Dict[str, int] = dict.fromkeys(
            ('messages', 'batches', 'rows_to_localizer', 'partly_rejected'), 0)
        self._tokens = itertools.count()
        self._rows: Dict[int, Tuple[NDArray[np.int64], NDArray[np.float64]]] = {}
        self._map = self.fuser.snapshot()
        self._version = 0
        self._map_version = [-1] * len(names)

    # --------------------------------------------------------------------- inputs
    def start(self, robot: int, stamp_ns: int, x: NDArray[np.float64],
              P: NDArray[np.float64]) -> None:
        """Give a robot its starting pose ``x`` (3,), ``P`` (3, 3) at ``stamp_ns``."""
        self.localizers[robot].initialize(stamp_ns, x, P)
        self.observers[robot].add_pose(stamp_ns, x, P, now_ns=stamp_ns)

    def odometry(self, robot: int, stamp_ns: int, pose: Optional[NDArray[np.float64]] = None,
                 twist: Optional[NDArray[np.float64]] = None) -> Optional[Estimate]:
        """
        Predict a robot's pose to an odometry message; place what its pose unblocks.

        Returns the robot's estimate at ``stamp_ns`` after the sightings placed (None
        when the localizer dropped the message).
        """
        loc = self.localizers[robot]
        est = loc.add_odometry(stamp_ns, pose=pose, twist=twist)
        if est is None:
            return None
        for batch in self.observers[robot].add_pose(stamp_ns, est.x, est.P, now_ns=stamp_ns):
            self._place(robot, batch)
        est = loc.estimate()
        self.tracks[robot].append(est)
        return est

    def sightings(self, robot: int, stamp_ns: int, ids: NDArray[np.int64],
                  z: NDArray[np.float64]) -> None:
        """
        Hand one sighting message (rows ``ids`` (N,), ``z`` (N, 2)) to the robot's observer.

        With ``hide_ids`` the message goes without its ``id`` column.
        """
        token = next(self._tokens)
        ids = np.asarray(ids, np.int64).reshape(-1)
        z = np.asarray(z, np.float64).reshape(-1, 2)
        self._rows[token] = (ids, z)
        columns = {'range': z[:, 0], 'bearing': z[:, 1]}
        if not self.config.hide_ids:
            columns['id'] = ids
        self.counts['messages'] += 1
        message = ObservationMessage(int(stamp_ns), columns, token=token)
        for batch in self.observers[robot].add_observations([message], now_ns=int(stamp_ns)):
            self._place(robot, batch)

    def robot_sighting(self, robot: int, stamp_ns: int, other: int,
                       z: NDArray[np.float64]) -> bool:
        """Apply a sighting ``z`` (2,) of robot ``other``; return whether its pose was there."""
        estimate = self.localizers[other].pose_at(int(stamp_ns))
        if estimate is None:
            return False
        self.localizers[robot].add_robot_sighting(int(stamp_ns), z, estimate,
                                                  other_id=self.names[other])
        return True

    # ------------------------------------------------------------------- the loop
    def _place(self, robot: int, batch: LandmarkBatch) -> None:
        """Fuse a placed batch; then update the robot's localizer against the prior map."""
        ids, z = self._rows.pop(batch.token)
        self.counts['batches'] += 1
        before, version = self._map, self._version
        if self.fuser.association_log is not None:
            self.fuser.association_log.clear()
        if len(batch.ids):
            self.dependent_stddevs.append(dependent_stddev(batch.P_dep))
            source = self.sources[robot][self.precision_source(batch.P_dep)]
            self.fuser.add_landmarks(source, LandmarkMessage(
                batch.stamp_ns, batch.ids, batch.m, batch.P, batch.P_dep,
                classes=batch.classes, scan=batch.scan))
            self.fuser.fuse_queued()
            if self.fuser.map_changed:
                self._map = self.fuser.snapshot()
                self._version += 1
        if self.config.hide_ids and self.config.association == 'localizer':
            ids = np.full(len(z), UNKNOWN_ID, np.int64)
        elif self.config.hide_ids:
            if len(batch.ids) != len(ids) or not self.fuser.association_log:
                self.counts['partly_rejected'] += len(batch.ids) != len(ids)
                return
            ids = np.array([self.fuser.tracker.resolve(i) if i >= 0 else UNKNOWN_ID
                            for i in self.fuser.association_log[-1][2].tolist()], np.int64)
        loc = self.localizers[robot]
        if self._map_version[robot] != version:
            loc.set_map(before.ids, before.m, before.P)
            self._map_version[robot] = version
        self.counts['rows_to_localizer'] += loc.add_observations(batch.stamp_ns, ids, z)

    def precision_source(self, P_dep: NDArray[np.float64]) -> int:
        """Return the precision level of a message (``observer.precision``) by its ``P_dep``."""
        observer = self.config.observer
        return precision_level(P_dep, observer.precision_sources, observer.precision_base_m)

    def map_records(self) -> List[dict]:
        """Return the fused map's confirmed landmarks (``LandmarkMap.to_records``)."""
        return self.fuser.map.to_records()

    def map_snapshot(self):
        """Return the fused map the localizers get (``Fuser.snapshot``: ids, m, P)."""
        return self.fuser.snapshot()

    def estimate(self, robot: int) -> Optional[Estimate]:
        """Return the robot's current pose and covariance (``Localizer.estimate``)."""
        return self.localizers[robot].estimate()

    def robot_counts(self, robot: int) -> dict:
        """Return a robot's localizer counters (``rows_used``, ``rows_gated``...)."""
        return dict(self.localizers[robot].counters.counts)
