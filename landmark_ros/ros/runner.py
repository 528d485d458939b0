"""The console entry point every node of the package shares."""

import signal
import sys

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException


def run(node_class, name, args=None, startup_errors=(), what='invalid parameters'):
    """
    Run one node until shutdown, as every console script of the package does.

    Parameters
    ----------
    node_class : type
        The Node subclass; constructed without arguments.
    name : str
        For the error message.
    args : list of str, optional
        Command-line arguments for ``rclpy.init``.
    startup_errors : tuple of exception types
        Besides invalid parameters, errors at construction that end the process with
        a message and exit code 2 instead of a traceback.
    what : str
        What the message says went wrong.

    Returns
    -------
    int
        0 after a normal shutdown (Ctrl-C, SIGTERM, external shutdown), 2 if the
        node could not start.

    """
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        # Started in the background of a script: SIGINT (what launchers send to stop
        # a node) would otherwise be ignored.
        signal.signal(signal.SIGINT, signal.default_int_handler)
    rclpy.init(args=args)
    node = None
    try:
        node = node_class()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, ParameterException, *startup_errors) as error:
        if node is not None and not rclpy.ok():
            return 0  # a stop signal during a callback: a clean stop all the same
        print(f'{name}: {what}: {error}', file=sys.stderr)
        return 2
    except Exception:  # noqa: B902 - see below
        # rclpy raises from inside the executor when a stop signal invalidates the
        # context in the middle of a take or a publish: that is a clean stop too.
        if node is not None and not rclpy.ok():
            return 0
        raise
    finally:
        if node is not None:
            try:
                node.destroy_node()
            except Exception:  # noqa: B902 - a node half torn down by the stop signal
                if rclpy.ok():
                    raise
        rclpy.try_shutdown()
    return 0
