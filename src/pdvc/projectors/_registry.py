"""Projector backends by name.

A backend is an object with ``name`` and the methods ``forward``,
``backproject``, ``jacobian`` and ``reduce`` of :class:`NumbaBackend` (same
arguments, same outputs within tolerance).  The CPU backend is always
present; optional ones (a GPU backend) register themselves when their
dependencies import.  ``"auto"`` picks the first available in preference
order and logs its choice; an explicit name never falls back.
"""

from __future__ import annotations

import logging
from typing import Callable

from ..errors import BackendError

__all__ = ["register_backend", "get_backend", "available_backends"]

log = logging.getLogger(__name__)

_FACTORIES: dict[str, Callable[[], object]] = {}
_PREFERENCE: list[str] = []
_INSTANCES: dict[str, object] = {}


def register_backend(name: str, factory: Callable[[], object], *, prefer: bool = False) -> None:
    """Make a backend available under ``name``.

    ``factory()`` builds it, raising ``ImportError``/``RuntimeError`` if its
    dependencies or device are missing. ``prefer=True`` puts it before the
    others for ``"auto"``.
    """
    _FACTORIES[name] = factory
    if name in _PREFERENCE:
        _PREFERENCE.remove(name)
    _PREFERENCE.insert(0 if prefer else len(_PREFERENCE), name)
    _INSTANCES.pop(name, None)


def _instantiate(name: str):
    if name not in _INSTANCES:
        _INSTANCES[name] = _FACTORIES[name]()
    return _INSTANCES[name]


def available_backends() -> list[str]:
    """Names of the backends that can be built here, in preference order."""
    names = []
    for name in _PREFERENCE:
        try:
            _instantiate(name)
        except (ImportError, RuntimeError):
            continue
        names.append(name)
    return names


def get_backend(name="auto"):
    """The backend called ``name`` (or an instance, passed through).

    ``"auto"`` returns the first available backend in preference order.
    """
    if not isinstance(name, str):
        return name
    if name == "auto":
        for cand in _PREFERENCE:
            try:
                backend = _instantiate(cand)
            except (ImportError, RuntimeError) as exc:
                log.info("projector backend %r unavailable (%s)", cand, exc)
                continue
            log.debug("projector backend 'auto' -> %r", cand)
            return backend
        raise BackendError("no projector backend is available")  # pragma: no cover
    if name not in _FACTORIES:
        raise BackendError(
            f"backend must be one of {sorted(_FACTORIES) + ['auto']}, got {name!r}"
        )
    try:
        return _instantiate(name)
    except (ImportError, RuntimeError) as exc:
        raise BackendError(
            f"backend {name!r} is registered but cannot be used here: {exc}; "
            f"available: {available_backends()}"
        ) from exc
