"""
The simulated world: landmarks, loop paths, visibility and the seeded random streams.

ROS-free (numpy only), used by ``simulation.Simulation``. Every random draw comes from
``rng(seed, stream, ...)``: a pure function of the run's seed and what is drawn, so a
draw does not depend on the draws before it.
"""

from dataclasses import dataclass
import math

from landmark_ros.core import pose2
from landmark_ros.core.sensors import MIN_RANGE
import numpy as np

MAX_ID = 2 ** 32 - 1
"""Largest landmark ID the ``landmarks`` schema (UINT32) can carry."""

_WORLD, _PATH, _BIAS, _POSE, _NOISE, _DETECTION, _CLUTTER, _FRAME = range(8)
"""Stream numbers of the random draws (part of each draw's seed)."""


def rng(seed, *stream):
    """
    Return the random generator of one stream of draws.

    Parameters
    ----------
    seed : int
        Seed of the run.
    *stream : int
        What is drawn (``_POSE``, ...), for which robot, at which index.

    Returns
    -------
    numpy.random.Generator

    """
    return np.random.default_rng([int(seed), *[int(s) for s in stream]])


# World ------------------------------------------------------------------------------

@dataclass(frozen=True)
class World:
    """The landmarks and the rectangle the robots drive in."""

    ids: np.ndarray
    """Landmark IDs, int64, shape (L,), sorted."""
    positions: np.ndarray
    """Landmark positions [m], shape (L, 2)."""
    bounds: tuple
    """``(x_min, y_min, x_max, y_max)`` of the area the paths stay in [m]."""

    def truth(self):
        """Return ``id -> (x, y)``, as ``evaluation.evaluate`` takes it."""
        return {int(i): tuple(p) for i, p in zip(self.ids.tolist(), self.positions)}


def generate_world(count, size, seed):
    """
    Place ``count`` landmarks uniformly in a square, apart from each other.

    Parameters
    ----------
    count : int
        Number of landmarks; their IDs are ``1 .. count``.
    size : float
        Side of the square, centred on the origin [m].
    seed : int
        Seed of the draw.

    Returns
    -------
    World

    """
    generator = rng(seed, _WORLD)
    half = 0.5 * size
    margin = 0.05 * size
    # Keep landmarks apart (when there is room) so that their ellipses do not overlap.
    spacing = 0.5 * size / math.sqrt(count)
    points = []
    while len(points) < count:
        candidates = generator.uniform(-half + margin, half - margin, (4 * count, 2))
        for point in candidates:
            if len(points) == count:
                break
            if not points or np.min(np.hypot(*(np.array(points) - point).T)) >= spacing:
                points.append(point)
        spacing *= 0.8
    return World(np.arange(1, count + 1, dtype=np.int64), np.array(points).reshape(-1, 2),
                 (-half, -half, half, half))


def load_world(path, min_size=1.0):
    """
    Read landmarks from a YAML file.

    The file holds a list of ``{id: int, x: float, y: float}``, either at the top
    level or under a ``landmarks`` key. The robots drive in the bounding box of the
    landmarks, grown by 10 % and to at least ``min_size`` on each side.

    Parameters
    ----------
    path : str
        YAML file.
    min_size : float
        Smallest side of the driving area [m].

    Returns
    -------
    World

    Raises
    ------
    ValueError
        If the file is not such a list, an ID repeats or is out of the UINT32
        range, or a coordinate is not a finite number.
    OSError
        If the file cannot be read.

    """
    import yaml
    with open(path) as stream:
        try:
            document = yaml.safe_load(stream)
        except yaml.YAMLError as error:
            raise ValueError(f'{path}: not valid YAML: {error}') from error
    if isinstance(document, dict):
        document = document.get('landmarks')
    if not isinstance(document, list) or not document:
        raise ValueError(f'{path}: expected a non-empty list of {{id, x, y}}')
    ids, positions = [], []
    for index, entry in enumerate(document):
        if not isinstance(entry, dict) or not {'id', 'x', 'y'} <= set(entry):
            raise ValueError(f'{path}: entry {index} is not a mapping with id, x and y')
        landmark_id, x, y = entry['id'], entry['x'], entry['y']
        if isinstance(landmark_id, bool) or not isinstance(landmark_id, int) \
                or not 0 <= landmark_id <= MAX_ID:
            raise ValueError(f'{path}: entry {index}: id must be an integer in '
                             f'[0, {MAX_ID}], got {landmark_id!r}')
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                   and math.isfinite(v) for v in (x, y)):
            raise ValueError(f'{path}: entry {index}: x and y must be finite numbers')
        ids.append(landmark_id)
        positions.append((float(x), float(y)))
    if len(set(ids)) != len(ids):
        raise ValueError(f'{path}: landmark IDs repeat')
    order = np.argsort(ids)
    ids = np.array(ids, dtype=np.int64)[order]
    positions = np.array(positions)[order]
    low, high = positions.min(axis=0), positions.max(axis=0)
    centre = 0.5 * (low + high)
    half = np.maximum(0.55 * (high - low), 0.5 * min_size)
    return World(ids, positions, (*(centre - half), *(centre + half)))


# Paths ------------------------------------------------------------------------------

@dataclass(frozen=True)
class LoopPath:
    """
    A smooth closed path driven at a constant parameter rate.

    ``kind`` ``'ellipse'`` is ``(a cos u, b sin u)``; ``'eight'`` (a Lissajous 1:2
    figure eight) is ``(a sin u, b sin 2u)``; both rotated by ``rotation`` and moved
    to ``centre``, with ``u = phase + direction * omega * t``.
    """

    kind: str
    centre: tuple
    """Centre [m]."""
    axes: tuple
    """Half extents ``(a, b)`` before the rotation [m]."""
    rotation: float
    """[rad]."""
    phase: float
    """Parameter at ``t = 0`` [rad]."""
    direction: int
    """+1 or -1."""
    omega: float
    """Parameter rate [rad/s]."""

    @property
    def period(self):
        """Time of one loop [s]."""
        return 2.0 * math.pi / self.omega

    def _local(self, u):
        a, b = self.axes
        if self.kind == 'ellipse':
            return (a * np.cos(u), b * np.sin(u)), (-a * np.sin(u), b * np.cos(u))
        return (a * np.sin(u), b * np.sin(2.0 * u)), (a * np.cos(u), 2.0 * b * np.cos(2.0 * u))

    def pose(self, t):
        """
        Return the pose at time ``t``; the heading is the direction of travel.

        Parameters
        ----------
        t : float or array_like, shape (N,)
            Time [s].

        Returns
        -------
        ndarray, shape (3,) or (N, 3)
            ``(x [m], y [m], heading [rad])``.

        """
        t = np.asarray(t, dtype=np.float64)
        u = self.phase + self.direction * self.omega * t
        (x, y), (dx, dy) = self._local(u)
        cos, sin = math.cos(self.rotation), math.sin(self.rotation)
        dx, dy = self.direction * dx, self.direction * dy
        return np.stack([self.centre[0] + cos * x - sin * y,
                         self.centre[1] + sin * x + cos * y,
                         pose2.wrap_angle(np.arctan2(sin * dx + cos * dy,
                                                     cos * dx - sin * dy))], axis=-1)

    def length(self, samples=4096):
        """Return the length of one loop [m]."""
        u = np.linspace(0.0, 2.0 * math.pi, samples + 1)
        (x, y), _ = self._local(u)
        return float(np.sum(np.hypot(np.diff(x), np.diff(y))))


def make_paths(robots, bounds, speed, seed):
    """
    Return one loop per robot inside ``bounds``, with distinct shapes and phases.

    Robots alternate between ellipses and figure eights and between the two
    directions of travel; sizes, rotations, centres and phases are drawn per robot.

    Parameters
    ----------
    robots : int
        Number of robots.
    bounds : tuple of float
        ``(x_min, y_min, x_max, y_max)`` [m].
    speed : float
        Mean speed along the path [m/s].
    seed : int
        Seed of the draws.

    Returns
    -------
    list of LoopPath

    """
    x_min, y_min, x_max, y_max = bounds
    width, height = x_max - x_min, y_max - y_min
    paths = []
    for i in range(robots):
        generator = rng(seed, _PATH, i)
        kind = ('ellipse', 'eight', 'ellipse')[i % 3]
        direction = 1 if i % 2 == 0 else -1
        scale = min(width, height)
        axes = (generator.uniform(0.25, 0.38) * scale, generator.uniform(0.15, 0.3) * scale)
        if kind == 'eight':
            axes = (axes[0], 0.5 * axes[1] + 0.05 * scale)
        rotation = generator.uniform(0.0, math.pi)
        phase = generator.uniform(0.0, 2.0 * math.pi)
        probe = LoopPath(kind, (0.0, 0.0), axes, rotation, 0.0, 1, 1.0)
        outline = probe.pose(np.linspace(0.0, 2.0 * math.pi, 721))[:, :2]
        # Move the centre at random as far as the outline stays 5 % inside the bounds.
        margin = 0.05 * scale
        low = np.array([x_min, y_min]) + margin - outline.min(axis=0)
        high = np.array([x_max, y_max]) - margin - outline.max(axis=0)
        centre = np.where(low <= high, generator.uniform(np.minimum(low, high),
                                                         np.maximum(low, high)),
                          0.5 * (low + high))
        omega = 2.0 * math.pi * speed / probe.length()
        paths.append(LoopPath(kind, (float(centre[0]), float(centre[1])),
                              (float(axes[0]), float(axes[1])), float(rotation),
                              float(phase), direction, float(omega)))
    return paths


def visible(pose, positions, min_range, max_range, fov):
    """
    Return which landmarks a sensor at ``pose`` measures.

    Parameters
    ----------
    pose : array_like, shape (3,)
        Sensor pose ``(x [m], y [m], heading [rad])``.
    positions : array_like, shape (L, 2)
        Landmark positions [m].
    min_range, max_range : float
        Range limits [m], inclusive.
    fov : float
        Field of view centred on the heading [rad]; ``2 pi`` sees all around.

    Returns
    -------
    mask : ndarray of bool, shape (L,)
    z : ndarray, shape (L, 2)
        True ``(range [m], bearing [rad])`` of every landmark.

    """
    pose = np.asarray(pose, dtype=np.float64)
    d = np.asarray(positions, dtype=np.float64).reshape(-1, 2) - pose[:2]
    r = np.hypot(d[:, 0], d[:, 1])
    bearing = pose2.wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - pose[2])
    mask = (r >= max(min_range, MIN_RANGE)) & (r <= max_range) & (
        np.abs(bearing) <= 0.5 * fov)
    return mask, np.stack([r, np.atleast_1d(bearing)], axis=-1)
