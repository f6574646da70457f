"""User-error types shared by modules that must not import each other (a leaf module)."""
from __future__ import annotations


class MethodError(ValueError):
    """Unknown method name or bad method option (a user error)."""
