"""Picture of a localization run: paths against the truth, 2-sigma ellipses (matplotlib)."""

import numpy as np

COLOURS = ('tab:blue', 'tab:orange', 'tab:green', 'tab:red', 'tab:purple')


def plot_run(path, dataset, tracks, title, ellipse_every_s=20.0, landmarks=None):
    """
    Draw every robot's estimated path over its true path, with position ellipses.

    Parameters
    ----------
    path : str or Path
        Output file (PNG, PDF...).
    dataset : mrclam.data.Dataset
        For the true landmarks.
    tracks : list of mrclam.localize.Track
        One per robot: estimates and truth at the odometry stamps.
    title : str
        Figure title.
    ellipse_every_s : float
        Time between two drawn 2-sigma ellipses [s].
    landmarks : list of dict, optional
        Map records (``LandmarkMap.to_records``: ``mean``, ``covariance``) drawn with
        their 2-sigma ellipses.

    Raises
    ------
    landmark_ros.eval.plotting.PlotUnavailableError
        If matplotlib is not installed.

    """
    from landmark_ros.eval import plotting
    fig, ax = plotting.new_figure((11.0, 7.0))
    truth = np.array([dataset.landmarks[i] for i in sorted(dataset.landmarks)]).reshape(-1, 2)
    ax.plot(truth[:, 0], truth[:, 1], 'k+', markersize=9, label='landmarks')
    for k, track in enumerate(tracks):
        colour = COLOURS[k % len(COLOURS)]
        step = max(1, len(track.times) // 3000)
        ax.plot(track.truth[::step, 0], track.truth[::step, 1], color=colour, alpha=0.3,
                linewidth=0.6)
        ax.plot(track.x[::step, 0], track.x[::step, 1], color=colour, linewidth=0.8,
                label=f'robot {track.robot}')
        if len(track.times):
            marks = np.searchsorted(track.times, np.arange(track.times[0], track.times[-1],
                                                           ellipse_every_s))
            for i in marks:
                plotting.draw_ellipse(ax, track.x[i, :2], track.P[i, :2, :2], 2.0,
                                      color=colour, linewidth=0.8)
    for k, record in enumerate(landmarks or ()):
        plotting.draw_ellipse(ax, record['mean'], record['covariance'], 2.0, color='k',
                              linewidth=1.2, label='map (2 sigma)' if k == 0 else None)
    ax.plot([], [], color='0.5', alpha=0.4, label='truth (faint)')
    ax.set_aspect('equal', adjustable='datalim')
    plotting.finish(fig, ax, path, title)
