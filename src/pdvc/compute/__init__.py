"""pdvc's operators on a Dask cluster (``dask.distributed``), optional.

``scheduler = "threads"`` (the default) is this process's threads, as if
this package did not exist. ``"local:N"`` starts a local cluster of N worker
processes; ``"tcp://host:port"`` uses a running one. Inside
:func:`use_scheduler`, :func:`pdvc.forward`, :func:`pdvc.reduce_views`,
:func:`pdvc.fdk` / :func:`pdvc.fbp` and
:func:`pdvc.calibration.per_view_snr` run on the cluster and give the same
numbers; :func:`pdvc.calibrate` takes ``scheduler=``. Dask is imported only
when a cluster is asked for (``pip install 'pdvc[dask]'``). See
``docs/distributed.md`` for the cost model.
"""

from ._scheduler import (
    DEFAULT_CONNECT_TIMEOUT_S,
    SchedulerError,
    SchedulerSpec,
    SchedulerUnreachableError,
    current_session,
    parse_scheduler,
    scheduler_keyword,
    use_scheduler,
)

__all__ = [
    "use_scheduler",
    "parse_scheduler",
    "current_session",
    "scheduler_keyword",
    "SchedulerSpec",
    "SchedulerError",
    "SchedulerUnreachableError",
    "ComputeError",
    "DaskSession",
    "DEFAULT_CONNECT_TIMEOUT_S",
]


def __getattr__(name):  # the Dask-side classes without importing Dask-side code up front
    if name in ("ComputeError", "DaskSession"):
        from . import _session

        return getattr(_session, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
