"""
The console entry point every node of the package shares.

``run`` handles the command line the way users expect of a ROS tool: ``-h`` /
``--help`` before ``--ros-args`` print the usage (topics, parameter file, every
parameter with its type, default and range) and exit 0; a missing parameter file, a
remap or override rcl cannot parse, an unknown argument or an invalid parameter give
one line on stderr and exit code 2, never a traceback.
"""

import faulthandler
import importlib
import os
import signal
import sys
import tempfile
import textwrap
import time

from landmark_ros.ros.fast_io import SWITCH_HELP
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

USAGE_ERROR = 2
"""Exit code of a command line or parameter the node cannot start with."""

STOP_DEADLINE_S = 10.0
"""Wall time a node has to tear down once its spin has ended [s]: then it dumps every
thread's stack and exits with code 1 (``nodes.start.stop_watchdog``)."""

NODE_CONFIGS = {
    'landmark_observer': ('landmark_ros.pipeline.config', 'ObserverConfig', 'observer.yaml'),
    'landmark_fuser': ('landmark_ros.pipeline.config', 'FuserConfig', 'fuser.yaml'),
    'landmark_sim': ('landmark_ros.sim.simulation', 'SimConfig', 'sim.yaml'),
}
"""Per executable: module and name of its config class, its shipped parameter file."""


def split_arguments(argv):
    """
    Split a command line into the arguments before and inside ``--ros-args``.

    Parameters
    ----------
    argv : list of str
        The command line without the program name.

    Returns
    -------
    own : list of str
        Arguments outside every ``--ros-args ... [--]`` block.
    ros : list of str
        Arguments inside them.

    """
    own, ros, inside = [], [], False
    for arg in argv:
        if arg == '--ros-args':
            inside = True
        elif inside and arg == '--':
            inside = False
        else:
            (ros if inside else own).append(arg)
    return own, ros


def usage(node_class, name):
    """
    Return the ``--help`` text of a node.

    Parameters
    ----------
    node_class : type
        The Node subclass; its module docstring describes the topics.
    name : str
        The executable (and default node) name.

    Returns
    -------
    str

    """
    text = [f'usage: {name} [-h] [--ros-args [-r __ns:=/NAMESPACE] [-r FROM:=TO] '
            '[--params-file FILE] [-p NAME:=VALUE] ...]', '']
    doc = sys.modules[node_class.__module__].__doc__ or ''
    text += [doc.strip(), '']
    if name in NODE_CONFIGS:
        from landmark_ros.ros.params import parameter_help
        module, class_name, params_file = NODE_CONFIGS[name]
        config_class = getattr(importlib.import_module(module), class_name)
        text += [
            'Parameter file: config/' + params_file + ' of the package, installed as',
            f'  $(ros2 pkg prefix --share landmark_ros)/config/{params_file}:',
            f'  {name} --ros-args --params-file FILE -p NAME:=VALUE',
            f"Its section '/**/{name}' applies to every node named {name} in any "
            'namespace;',
            'a node renamed with -r __node:=OTHER reads the section of OTHER instead.',
            'Integers are accepted for doubles (range_stddev:=1, sensor_pose:=[0, 0, 1]);',
            'a list must not mix them: [0.0, 0, 1] is refused, write [0.0, 0.0, 1.0].',
            '', 'Parameters:', parameter_help(config_class),
            textwrap.fill(SWITCH_HELP, 79, initial_indent='  ', subsequent_indent='      ')]
    return '\n'.join(text) + '\n'


def _error(name, text):
    print(f'{name}: {text}', file=sys.stderr)
    return USAGE_ERROR


def _rcl_message(error):
    """Return the first sentence of an rcl initialisation error, without source locations."""
    text = str(error).replace('failed to initialize rcl: ', '')
    text = text.split(', at /')[0].strip()
    if 'Sequence should be of same type' in text:
        text += ('; every entry of a list must have the same type: write doubles with a '
                 'decimal point, e.g. [0.0, 0.0, 1.0]')
    return text


def _init(args, name):
    """
    Initialise rclpy; return None or the one-line reason it refused the command line.

    rcl logs its own 'Failed to parse global arguments' line on stderr before the
    exception; it is kept only when initialisation succeeds (nothing to hide then).
    """
    saved = os.dup(2)
    with tempfile.TemporaryFile() as captured:
        sys.stderr.flush()
        os.dup2(captured.fileno(), 2)
        try:
            rclpy.init(args=args)
            failure = None
        except RuntimeError as error:   # rclpy's RCLError (in rclpy's private module)
            failure = _rcl_message(error)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        if failure is None:
            captured.seek(0)
            sys.stderr.write(captured.read().decode(errors='replace'))
    return failure


_STOPS = []
"""The SIGINTs received (``_stop_requested``): one before rclpy's handler is there
must still stop the node."""


def _stop_requested(signum, frame):
    """Python's part of SIGINT and SIGTERM: note it (rclpy's handler shuts the context down)."""
    _STOPS.append(signum)


def _stopping(node, wait_s=1.0):
    """
    Return whether a stop signal is shutting the context down (after a failure in spin).

    rclpy shuts the context down from its signal thread, so an error the signal
    caused in the executor (a take interrupted in the middle: pybind11's "Unable to
    convert call argument") can come just before ``rclpy.ok()`` turns False: wait up
    to ``wait_s`` for it.
    """
    if node is None:     # failed while being built: stopped if the context is down
        return not rclpy.ok()
    deadline = time.monotonic() + wait_s
    while rclpy.ok() and time.monotonic() < deadline:
        time.sleep(0.01)
    return not rclpy.ok()


def run(node_class, name, args=None, startup_errors=(), what='invalid parameters'):
    """
    Run one node until shutdown, as every console script of the package does.

    Parameters
    ----------
    node_class : type
        The Node subclass; constructed without arguments.
    name : str
        The executable name, for the help and the error messages.
    args : list of str, optional
        Command line for ``rclpy.init``, program name first; ``sys.argv`` by default.
    startup_errors : tuple of exception types
        Besides invalid parameters, errors at construction that end the process with
        a message and exit code 2 instead of a traceback.
    what : str
        What the message says went wrong.

    Returns
    -------
    int
        0 after a normal shutdown (Ctrl-C, SIGTERM, external shutdown) or ``--help``,
        2 if the command line is wrong or the node could not start.

    """
    argv = list(sys.argv if args is None else args)
    own, ros = split_arguments(argv[1:])
    if '-h' in own or '--help' in own:
        sys.stdout.write(usage(node_class, name))
        return 0
    if own:
        return _error(name, f'unknown argument {own[0]!r}: ROS arguments go after '
                            '--ros-args (see --help)')
    for flag, value in zip(ros, ros[1:]):
        if flag == '--params-file' and not os.path.isfile(value):
            return _error(name, f'parameter file not found: {value}')
    # SIGINT stops the node through rclpy, whose handler (installed by init, on top
    # of this one) shuts the context down: spin then ends. Python's own handler would
    # also raise KeyboardInterrupt wherever the main thread is, inside a pybind11 take
    # or a garbage-collected llvmlite object's __del__ ("Exception ignored" and a
    # traceback on stderr); this one does not raise. (It also replaces SIG_IGN, which
    # a node started in the background of a script would otherwise keep.)
    # The same for SIGTERM: the console scripts' entry (nodes.start) makes both end
    # the process at once while it imports, which must not outlive the imports
    # (rclpy's handlers call the previous one).
    _STOPS.clear()
    signal.signal(signal.SIGINT, _stop_requested)
    signal.signal(signal.SIGTERM, _stop_requested)
    failure = _init(argv, name)
    if failure is not None:
        return _error(name, f'bad command line: {failure}')
    if _STOPS:      # before rclpy's handler was installed: nobody shut the context down
        rclpy.try_shutdown()
        return 0
    node = executor = None
    try:
        # The executor first: one built on a context a stop signal just shut down
        # would print an "Exception ignored" traceback when collected.
        executor = SingleThreadedExecutor()
        node = node_class()
        if _STOPS:      # a stop while the node was built: no spin (DDS is closed below)
            return 0
        rclpy.spin(node, executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, ParameterException, *startup_errors) as error:
        if _stopping(node):
            return 0  # a stop signal during a callback: a clean stop all the same
        return _error(name, f'{what}: {error}')
    except Exception:  # noqa: B902 - see below
        # rclpy raises from inside the executor when a stop signal invalidates the
        # context in the middle of a take or a publish: that is a clean stop too.
        if _stopping(node):
            return 0
        raise
    finally:
        # A teardown that hangs ends the process (nodes.start.stop_watchdog).
        faulthandler.dump_traceback_later(STOP_DEADLINE_S, exit=True)   # C thread
        try:
            if executor is not None:
                executor.shutdown(timeout_sec=STOP_DEADLINE_S)
            if node is not None:
                try:
                    node.destroy_node()
                except Exception:  # noqa: B902 - a node half torn down by the stop signal
                    if rclpy.ok():
                        raise
            rclpy.try_shutdown()
        finally:
            faulthandler.cancel_dump_traceback_later()
    return 0
