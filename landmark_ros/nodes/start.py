"""
The console scripts' entry points: a node that Ctrl-C ends cleanly from its first line.

A node spends its first second or two importing (rclpy, numpy). Python's own SIGINT
handler would raise ``KeyboardInterrupt`` wherever the import is: a traceback, and
exit code 254 under ``ros2 run``. Each entry point here installs, before any heavy
import, a handler that ends the process at once with exit code 0 (nothing is open
yet to close); ``ros.runner.run`` replaces it with its own before ``rclpy.init``.
``python -m landmark_ros.nodes.NAME`` gets the same handler from the package's
``__init__``. Only the standard library is imported here.

``lazy`` defers a heavy module to its first use, so that a node creates its
endpoints before it imports the fusion or geometry code; ``imported`` runs that import in
a thread while watching for a stop signal.
"""

import faulthandler
import importlib
import importlib.util
import os
import signal
import sys
import threading


def _exit_now(signum, frame):
    """SIGINT or SIGTERM while the node imports: end the process, exit code 0."""
    os._exit(0)


def install():
    """
    Make SIGINT and SIGTERM end the process with exit code 0 until the runner takes over.

    Only before ``rclpy.init``: later a DDS participant exists, whose shared memory
    an ``os._exit`` would leave behind (``ros.runner.run`` installs its own handlers
    first).
    """
    signal.signal(signal.SIGINT, _exit_now)
    signal.signal(signal.SIGTERM, _exit_now)


EXIT_DEADLINE_S = 10.0
"""Wall time the interpreter has to exit once the node has stopped [s]."""


def stop_watchdog(seconds):
    """
    End the process in ``seconds`` unless it has ended by then: a stop that hangs.

    Tearing down DDS (the node's endpoints; the participant when the interpreter
    collects the context at exit) hung a node once, past ``ros2 launch``'s SIGTERM,
    which a stopped node ignores (``finish``). ``faulthandler``'s watchdog is a C
    thread, so it fires whatever holds the GIL: it writes every thread's Python stack
    to stderr (where it hung) and exits with code 1. ``ros.runner.run`` arms it for
    the teardown and disarms it when done; ``finish`` arms it for the exit.
    """
    faulthandler.dump_traceback_later(seconds, exit=True)


def finish(code):
    """
    Ignore SIGINT and SIGTERM from now on; return ``code`` (the node has stopped).

    Ctrl-C in a terminal signals the whole process group and ``ros2 launch`` forwards
    its own SIGINT, so a node gets a second one while it stops. Python's finalisation
    puts back the default action of every signal that has a Python handler, and a
    SIGINT then would end the process with -2; an ignored signal stays ignored. The
    exit has ``EXIT_DEADLINE_S`` (``stop_watchdog``).
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    stop_watchdog(EXIT_DEADLINE_S)
    return code


def _run(name):
    install()
    return finish(importlib.import_module(f'landmark_ros.nodes.{name}').main())


def observer():
    """Entry point of ``landmark_observer``."""
    return _run('observer')


def fuser():
    """Entry point of ``landmark_fuser``."""
    return _run('fuser')


def sim():
    """Entry point of ``landmark_sim``."""
    return _run('sim')


def localizer():
    """Entry point of ``landmark_localizer``."""
    return _run('localizer')


def lazy(name):
    """
    Return module ``name``, to be imported when one of its attributes is first used.

    The standard library's ``importlib.util.LazyLoader``; a module already imported
    is returned as it is.

    Parameters
    ----------
    name : str
        Absolute module name.

    Returns
    -------
    module

    """
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.find_spec(name)
    loader = importlib.util.LazyLoader(spec.loader)
    spec.loader = loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    loader.exec_module(module)
    return module


def imported(node, load):
    """
    Call ``load`` (an import) in a thread; return False if a stop signal comes first.

    The import takes a second or more (scipy); a stop signal shuts the node's context
    down but lets Python code run on, so the wait, not the import, watches for it.

    Parameters
    ----------
    node : rclpy.node.Node
        The node being built; its context tells whether a stop signal came.
    load : callable
        Imports what the node needs (its first use of a ``lazy`` module).

    Returns
    -------
    bool
        True once ``load`` has returned, False if the context shut down first.

    """
    loader = threading.Thread(target=load, daemon=True,
                              name=f'{node.get_name()}.import')
    loader.start()
    while loader.is_alive():
        loader.join(0.05)
        if not node.context.ok():
            return False
    return True
