"""
Matplotlib drawing of robots and landmark estimates (matplotlib is optional).

Install the extra ``landmark_ros[plot]`` (or matplotlib) to use it; the rest of
the package never imports it.
"""

from landmark_ros.core import pose2
from landmark_ros.core.ellipse import ellipse_points
import numpy as np

ROBOT_TRIANGLE = np.array([[0.6, 0.0], [-0.3, 0.3], [-0.3, -0.3]])
"""A robot's outline in its own frame, for unit ``size`` [m]."""


class PlotUnavailableError(RuntimeError):
    """Plotting was asked for but matplotlib is not installed."""


def new_figure(figsize=(8.0, 7.0)):
    """
    Return a figure and its axes, drawn off-screen (no display needed).

    Raises
    ------
    PlotUnavailableError
        If matplotlib is not installed.

    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise PlotUnavailableError(
            'plotting needs matplotlib, the optional extra landmark_ros[plot]: '
            'pip install "landmark_ros[plot]" (or pip install matplotlib)') from exc
    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig, fig.add_subplot()


def draw_ellipse(ax, m, P, sigma=1.0, **style):
    """
    Draw the ``sigma`` contour of a 2D Gaussian.

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        Where to draw.
    m : array_like, shape (2,)
        Centre [m].
    P : array_like, shape (2, 2)
        Covariance [m^2].
    sigma : float
        Size in standard deviations.
    **style
        Passed to ``ax.plot``.

    """
    ring = ellipse_points(m, P, sigma, num_points=72)
    ring = np.vstack([ring, ring[:1]])
    return ax.plot(ring[:, 0], ring[:, 1], **style)


def draw_robot(ax, pose, P_pose=None, size=1.0, colour='tab:blue', label=None, sigma=1.0):
    """
    Draw a robot as an oriented triangle, with its (x, y) pose ellipse.

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        Where to draw.
    pose : array_like, shape (3,)
        Robot pose.
    P_pose : array_like, shape (3, 3), optional
        Its covariance; the (x, y) block is drawn.
    size : float
        Triangle size [m].
    colour : str
        Matplotlib colour.
    label : str, optional
        Legend entry.
    sigma : float
        Ellipse size in standard deviations.

    """
    from matplotlib.patches import Polygon
    pose = np.asarray(pose, dtype=np.float64)
    ax.add_patch(Polygon(pose2.transform_point(pose, size * ROBOT_TRIANGLE), closed=True,
                         facecolor=colour, edgecolor='black', label=label))
    if P_pose is not None:
        draw_ellipse(ax, pose[:2], np.asarray(P_pose)[:2, :2], sigma, color=colour,
                     linestyle='--', linewidth=1.0)


def finish(fig, ax, path, title=''):
    """Label equal axes, add a legend and write the figure to ``path``."""
    ax.set_title(title)
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    ax.set_aspect('equal', adjustable='datalim')
    ax.grid(True, alpha=0.4)
    ax.legend(loc='best', fontsize='small')
    fig.tight_layout()
    fig.savefig(path, dpi=120)
