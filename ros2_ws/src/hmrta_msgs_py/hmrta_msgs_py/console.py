"""The body of every HMRTA console script (``ros2 run`` and a pip install run the same ones).

A console script imports the module it names before it calls anything, and the node modules load
rclpy, numpy and, for the learned policy, torch at the top: a Ctrl-C in that first second would
end the process with a ``KeyboardInterrupt`` traceback. So the scripts name the light ``entry``
module of their package, whose functions import the node module here, inside :func:`run`: a
Ctrl-C at any moment of start-up is then one line on stderr and exit status 130, like a Ctrl-C
while a node loads its mission or policy (:func:`hmrta_msgs_py.runtime.starting`). A node that
is running handles Ctrl-C itself (:func:`hmrta_msgs_py.runtime.spin_nodes`)."""
from __future__ import annotations

import contextlib
import importlib
import signal
import sys
import threading
from typing import Iterator

# the Ctrl-Cs received since start-up began: a library that catches what an import raises (an
# optional C extension's ImportError, a bare except) may swallow the KeyboardInterrupt of one,
# and the process would go on as if it had not come; start-up checks this list at its steps
INTERRUPTED: list[int] = []


_DEFERRED = [0]  # open signals_deferred() blocks

SCRIPT: list[str] = []  # the console script's name, once run() started it (runtime.teardown_watchdog)


def _noted(sig: int, frame) -> None:
    INTERRUPTED.append(sig)
    if _DEFERRED[0]:
        return  # raised when the block ends (signals_deferred)
    raise KeyboardInterrupt  # as Python's own handler does for SIGINT (SIGTERM: the same path, said apart)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Within it, a start-up signal (Ctrl-C, SIGTERM) is noted and raised as KeyboardInterrupt
    only when the block ends: for work a KeyboardInterrupt must not cut short, such as torch's
    import, which aborts the whole process in C++ ("terminate called after throwing ...") when
    one is raised inside it. Keep such blocks short: the signal waits for them."""
    _DEFERRED[0] += 1
    try:
        yield
    finally:
        _DEFERRED[0] -= 1
    if INTERRUPTED and not _DEFERRED[0] and signal.getsignal(signal.SIGINT) is _noted:
        raise KeyboardInterrupt


def run(prog: str, module: str, func: str = "main") -> None:
    """Import ``module`` and exit with what its ``func()`` returns (None: 0). ``kill -USR1 PID``
    prints the Python stack of every thread of the process on its stderr (a node that seems
    stuck says where), and the process goes on; a fatal signal (a segmentation fault in the
    middleware, an abort) prints them too before the process dies of it, so its log says where.
    Once its nodes stop, the rest of its life is bounded
    (:func:`hmrta_msgs_py.runtime.teardown_watchdog`)."""
    import faulthandler

    SCRIPT[:] = [prog]
    if not faulthandler.is_enabled():
        faulthandler.enable(all_threads=True)
    if hasattr(signal, "SIGUSR1"):
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    if threading.current_thread() is threading.main_thread():
        # also over an inherited SIG_IGN (a `node &` of a shell script): a node stops on SIGINT,
        # in start-up as once it runs (where rclpy, and so every ROS node, takes SIGINT over)
        if signal.getsignal(signal.SIGINT) in (signal.default_int_handler, signal.SIG_IGN):
            signal.signal(signal.SIGINT, _noted)
        if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:  # (else it would end the process without a word)
            signal.signal(signal.SIGTERM, _noted)
    try:
        main = getattr(importlib.import_module(module), func)
        if INTERRUPTED:  # (swallowed while the module loaded)
            raise KeyboardInterrupt
        code = main()
    except KeyboardInterrupt:
        _interrupted(prog)
    except ImportError as e:
        from hmrta.errors import caused_by_interrupt  # a leaf module: nothing heavy

        if not caused_by_interrupt(e):
            raise
        _interrupted(prog)  # a C extension (rclpy's) interrupted while it initialises
    raise SystemExit(code)


def quiet_half_built_loggers() -> None:
    """A signal that interrupts rclpy while it builds a logger (``RcutilsLogger.__init__``)
    leaves one without its attributes, whose ``__del__`` then fails when the process exits,
    printing "Exception ignored in ... Traceback" after the one line that says the process was
    stopped. Such failures of rclpy's logger finalizer are not reported; every other unraisable
    exception is, as before."""
    if sys.unraisablehook is not _quiet_unraisable:
        _quiet_unraisable.previous = sys.unraisablehook
        sys.unraisablehook = _quiet_unraisable


def _quiet_unraisable(u) -> None:
    if getattr(u.object, "__qualname__", "") == "RcutilsLogger.__del__" and isinstance(u.exc_value, AttributeError):
        return
    _quiet_unraisable.previous(u)


def _interrupted(prog: str):
    runtime = sys.modules.get("hmrta_msgs_py.runtime")  # (not imported here: it loads rclpy)
    late = runtime is not None and getattr(runtime, "SPUN", False)  # a second Ctrl-C while the nodes stop
    stopped(prog, "" if late else " during start-up")


def stopped(prog: str, when: str = " during start-up"):
    """One line on stderr and the exit status of a process stopped by a signal before it ran:
    Ctrl-C (SIGINT) ``interrupted``, 130; SIGTERM ``terminated``, 143 (128 + the signal, as a
    shell reports a process the signal ended)."""
    from hmrta.errors import forget_handled_interrupt  # a leaf module: nothing heavy

    quiet_half_built_loggers()
    forget_handled_interrupt()  # (a process run as python -m would end with SIGINT, not this status)
    if INTERRUPTED and INTERRUPTED[-1] == signal.SIGTERM:
        print(f"{prog}: terminated{when} (SIGTERM)", file=sys.stderr)
        raise SystemExit(128 + signal.SIGTERM) from None
    print(f"{prog}: interrupted{when}", file=sys.stderr)
    raise SystemExit(130) from None
