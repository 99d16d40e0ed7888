"""numba's njit, or a pass-through decorator when numba is missing (slow but correct)."""

from __future__ import annotations

from typing import Any, Callable

try:
    from numba import njit
except ImportError:  # pragma: no cover - numba is a dependency; this keeps the planner usable.

    def njit(*args: Any, **kwargs: Any) -> Callable:  # type: ignore[no-redef]
        """Stand-in decorator that leaves the function as plain Python."""
        if args and callable(args[0]):
            return args[0]
        return lambda function: function

__all__ = ["njit"]
