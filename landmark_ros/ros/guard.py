"""Callbacks that cannot end a node: an unexpected exception is counted and logged."""

import functools
import traceback


def guarded(node, counters, callback, what):
    """
    Wrap a subscription, timer or service callback of ``node``.

    An exception the callback did not handle is counted as ``internal_error`` and
    logged with its traceback (throttled by ``counters``), and the node goes on. While
    the node's context is shutting down (a stop signal arrived in the middle of a
    callback) the exception is dropped without a word: the node is stopping anyway.

    Parameters
    ----------
    node : rclpy.node.Node
        The node the callback belongs to.
    counters : landmark_ros.pipeline.counters.Counters
        Where ``internal_error`` is counted.
    callback : callable
        The callback.
    what : str
        What it is, for the log line (``'observations callback'``).

    Returns
    -------
    callable
        The wrapped callback; for a service callback it returns the response unchanged
        when the callback failed (``success`` false where the response has one).

    """
    @functools.wraps(callback)
    def wrapper(*args):
        try:
            return callback(*args)
        except Exception:  # noqa: B902 - nothing an input can do may end the node
            if not node.context.ok():
                return _response(args)
            counters.add('internal_error', 1,
                         f'{what} failed; the node goes on:\n{traceback.format_exc()}')
            return _response(args)
    return wrapper


def _response(args):
    """Return the response argument of a service callback (None for other callbacks)."""
    if len(args) == 2 and hasattr(args[1], 'success'):
        args[1].success = False
        if hasattr(args[1], 'message'):
            args[1].message = 'internal error: see the log'
        return args[1]
    return None
