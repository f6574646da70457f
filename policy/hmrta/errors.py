"""User-error types shared by modules that must not import each other, and what an error came
from (a leaf module: the console scripts import it before anything heavy)."""
from __future__ import annotations


class MethodError(ValueError):
    """Unknown method name or bad method option (a user error)."""


def caused_by_interrupt(e: BaseException | None) -> bool:
    """Whether a KeyboardInterrupt is among the causes of ``e`` (pybind11 turns a Ctrl-C while an
    extension module initialises into ``ImportError: initialization failed`` caused by it)."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def forget_handled_interrupt() -> None:
    """Clear CPython's note of an unhandled KeyboardInterrupt once it has been handled.

    A KeyboardInterrupt raised inside code that a C extension runs with ``PyRun_String`` (rclpy's
    pybind11 module does while it loads, and Ray's) sets that note even when the interrupt is
    caught further up; a process started as ``python -m ...`` then ends by killing itself with
    SIGINT (status -2) instead of exiting with the status it chose (130 for a Ctrl-C). Any
    successful ``PyRun_String`` resets the note, so an empty one is run."""
    try:
        import ctypes

        ctypes.pythonapi.PyRun_SimpleString(b"")
    except (ImportError, AttributeError, OSError):  # not CPython, or no ctypes: nothing to clear
        pass
