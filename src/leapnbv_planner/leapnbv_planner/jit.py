"""numba's njit, or a pass-through decorator when numba is missing (slow but correct).

For a type checker ``njit(...)`` returns the function's own type: numba's dispatcher takes the
arguments and returns the values the Python function does (numba has no type stubs).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, TypeVar

F = TypeVar("F", bound=Callable[..., Any])

if TYPE_CHECKING:

    def njit(*args: Any, **kwargs: Any) -> Callable[[F], F]:
        """numba.njit(cache=..., ...) as a decorator that keeps the function's signature."""
        ...

else:
    try:
        from numba import njit
    except ImportError:  # pragma: no cover - numba is a dependency; this keeps the planner usable.

        def njit(*args: Any, **kwargs: Any) -> Callable[..., Any]:
            """Stand-in decorator that leaves the function as plain Python."""
            if args and callable(args[0]):
                return args[0]
            return lambda function: function

__all__ = ["njit"]
