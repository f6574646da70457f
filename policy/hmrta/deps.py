"""Optional dependencies: one place that turns a missing one into a one-line user error naming
the pip extra that brings it (``pip install 'hmrta[rl]'``)."""
from __future__ import annotations

import importlib
from types import ModuleType

from .errors import MethodError

# importable module -> the hmrta extra that installs it
EXTRAS = {"torch": "rl", "ortools": "cpsat", "ray": "ray", "matplotlib": "plot"}


class MissingDependency(MethodError):
    """An optional dependency is not installed (a user error: exit 2 with the install hint)."""


def require(module: str, what: str | None = None) -> ModuleType:
    """Import ``module`` or raise :class:`MissingDependency` naming what needs it and the extra."""
    try:
        return importlib.import_module(module)
    except ImportError:
        top = module.split(".")[0]
        extra = EXTRAS.get(top)
        hint = f"pip install 'hmrta[{extra}]'" if extra else f"pip install {top}"
        raise MissingDependency(f"{what or module} needs {top}, which is not installed ({hint})") from None
