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
