"""The error every bag function raises."""

from __future__ import annotations

__all__ = ["BagError"]


class BagError(Exception):
    """A bag could not be written, read or validated; the message names the path at fault."""
