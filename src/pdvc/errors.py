"""Exception hierarchy of pdvc.

Every error raised on purpose by pdvc derives from :class:`PdvcError`, and
also from the built-in class a Python user would expect (``ValueError``,
``TypeError``, ...), so ``except ValueError`` keeps working.  Messages name
the parameter, what was expected and what came.
"""

from __future__ import annotations


class PdvcError(Exception):
    """Base class of all pdvc errors."""


class GeometryError(PdvcError, ValueError):
    """An inconsistent or degenerate geometry (vectors, detector, volume)."""


class ShortScanError(GeometryError):
    """A cone-beam scan over less than a full turn whose arc is shorter than 180° plus the fan angle (no Parker weights)."""


class ShapeError(PdvcError, ValueError):
    """Arrays whose shapes do not agree with each other or with a geometry."""


class BackendError(PdvcError, ValueError):
    """An unknown or unavailable projector backend."""


class InputTypeError(PdvcError, TypeError):
    """An argument of the wrong type (e.g. a plain array where a geometry is expected)."""
