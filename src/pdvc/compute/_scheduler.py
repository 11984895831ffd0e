"""Which scheduler runs pdvc's operators: parsing, and the one current for a run.

``scheduler`` is a string everywhere a user sets it (``[compute] scheduler``,
``--scheduler``, ``scheduler=``):

* ``"threads"`` -- the threads of this process (numba), as without this module;
* ``"local:N"`` or ``"local:NxT"`` -- a Dask ``LocalCluster`` of ``N`` worker
  processes of ``T`` threads each (default 1), started and closed by pdvc;
* ``"tcp://host:port"`` (or ``tls://``) -- the scheduler of a running Dask
  cluster, which pdvc connects to and leaves running.

From Python a ``distributed.Client`` may also be given; pdvc uses it and
never closes it. Nothing here imports Dask: it is imported only when a
scheduler other than ``"threads"`` is asked for.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import inspect
import logging
import os
import re
from dataclasses import dataclass
from typing import Iterator, Optional

from ..errors import PdvcError

__all__ = [
    "SchedulerError",
    "SchedulerUnreachableError",
    "SchedulerSpec",
    "parse_scheduler",
    "use_scheduler",
    "current_session",
    "scheduler_keyword",
    "DEFAULT_CONNECT_TIMEOUT_S",
]

log = logging.getLogger("pdvc.compute")

#: Seconds to wait for the scheduler of an existing cluster before giving up.
DEFAULT_CONNECT_TIMEOUT_S = 5.0

_FORMS = "'threads', 'local:N' (N worker processes), 'local:NxT' (T threads each) or 'tcp://host:port'"


class SchedulerError(PdvcError, ValueError):
    """A ``scheduler`` setting that is malformed or cannot be used here (e.g. Dask is not installed)."""


class SchedulerUnreachableError(SchedulerError, ConnectionError):
    """The Dask scheduler at the address given did not answer."""


@dataclass(frozen=True)
class SchedulerSpec:
    """A parsed ``scheduler`` setting.

    Attributes
    ----------
    kind : {"threads", "local", "address", "client"}
    n_workers, threads_per_worker : int
        For ``"local"``.
    address : str
        For ``"address"``.
    client : distributed.Client or None
        For ``"client"`` (a client the caller owns).
    """

    kind: str
    n_workers: int = 0
    threads_per_worker: int = 1
    address: str = ""
    client: object = None

    def __str__(self) -> str:
        if self.kind == "local":
            return f"local:{self.n_workers}" + (f"x{self.threads_per_worker}" if self.threads_per_worker != 1 else "")
        if self.kind == "address":
            return self.address
        if self.kind == "client":
            return f"client of {getattr(self.client, 'scheduler_info', lambda: {})().get('address', '?')}"
        return "threads"


_LOCAL = re.compile(r"^local:(\d+)(?:x(\d+))?$")
_ADDRESS = re.compile(r"^(tcp|tls)://[^\s/:]+:(\d+)/?$")


def parse_scheduler(scheduler) -> SchedulerSpec:
    """Check a ``scheduler`` setting and say what it asks for.

    Parameters
    ----------
    scheduler : str, SchedulerSpec or distributed.Client
        ``"threads"``, ``"local:N"``, ``"local:NxT"``, ``"tcp://host:port"``
        (``None`` is ``"threads"``).

    Raises
    ------
    SchedulerError
        Anything else; the message names ``scheduler`` and the forms allowed.

    Examples
    --------
    >>> parse_scheduler("local:2")
    SchedulerSpec(kind='local', n_workers=2, threads_per_worker=1, address='', client=None)
    """
    if scheduler is None:
        return SchedulerSpec("threads")
    if isinstance(scheduler, SchedulerSpec):
        return scheduler
    if not isinstance(scheduler, str):
        if type(scheduler).__name__ == "Client" and hasattr(scheduler, "submit") and hasattr(scheduler, "scatter"):
            return SchedulerSpec("client", client=scheduler)
        raise SchedulerError(f"scheduler must be a string ({_FORMS}) or a distributed.Client, got {type(scheduler).__name__}")
    text = scheduler.strip()
    if text == "threads":
        return SchedulerSpec("threads")
    m = _LOCAL.match(text)
    if m:
        n, t = int(m.group(1)), int(m.group(2) or 1)
        if n < 1 or t < 1:
            raise SchedulerError(f"scheduler {scheduler!r}: local clusters need at least 1 worker of at least 1 thread")
        return SchedulerSpec("local", n_workers=n, threads_per_worker=t)
    m = _ADDRESS.match(text)
    if m:
        port = int(m.group(2))
        if not 0 < port < 65536:
            raise SchedulerError(f"scheduler {scheduler!r}: the port must be in 1..65535, got {port}")
        return SchedulerSpec("address", address=text.rstrip("/"))
    raise SchedulerError(f"scheduler must be {_FORMS}, got {scheduler!r}")


_CURRENT: contextvars.ContextVar = contextvars.ContextVar("pdvc_scheduler_session", default=None)


def current_session():
    """The :class:`~pdvc.compute.DaskSession` current in this context, or None (threads)."""
    return _CURRENT.get()


def _import_distributed():
    try:
        import distributed  # noqa: F401
    except ImportError as exc:
        raise SchedulerError(
            "scheduler other than 'threads' needs dask.distributed, which is not installed "
            f"({exc}); install it with: pip install 'pdvc[dask]' (or use scheduler = 'threads')"
        ) from None
    return distributed


def _start_local(spec: SchedulerSpec, distributed):
    """A LocalCluster of worker processes, each running one task at a time on ``threads_per_worker`` numba threads.

    (The kernels are compiled without ``nogil``: T Dask threads in one
    worker would take turns; T numba threads in one task use T cores.)
    """
    env = {
        "NUMBA_NUM_THREADS": str(spec.threads_per_worker),
        "OMP_NUM_THREADS": "1",
        "MKL_NUM_THREADS": "1",
        "OPENBLAS_NUM_THREADS": "1",
    }
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)  # the worker processes inherit it at their start, before numba reads it
    try:
        cluster = distributed.LocalCluster(
            n_workers=spec.n_workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},  # its HTTP endpoints on a free port, not 8787
            silence_logs=logging.ERROR,
            env=env,
        )
    except RuntimeError as exc:
        raise SchedulerError(
            f"scheduler {str(spec)!r}: the local cluster did not start ({exc}); in a script, start it from "
            "under `if __name__ == \"__main__\":` (worker processes re-import the main module)"
        ) from exc
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    try:
        client = distributed.Client(cluster, set_as_default=False)
        client.wait_for_workers(spec.n_workers, timeout=120)
    except BaseException:
        cluster.close()
        raise
    return cluster, client


def _connect(address: str, timeout: float, distributed):
    try:
        client = distributed.Client(address, timeout=timeout, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise SchedulerUnreachableError(
            f"scheduler {address!r}: no Dask scheduler answered at this address within {timeout:g} s "
            f"({type(exc).__name__}: {exc}); start one (dask scheduler / dask worker) or check the address"
        ) from None
    return client


@contextlib.contextmanager
def use_scheduler(scheduler="threads", *, connect_timeout: float = DEFAULT_CONNECT_TIMEOUT_S) -> Iterator[Optional[object]]:
    """Run pdvc's operators on ``scheduler`` for the duration of the ``with`` block.

    Inside the block, :func:`pdvc.forward`, :func:`pdvc.reduce_views`,
    :func:`pdvc.fdk`, :func:`pdvc.fbp` and
    :func:`pdvc.calibration.per_view_snr` run on the cluster; everything
    else is unchanged. A local cluster is started on entry and closed on
    exit; a cluster given by address or client is left running.

    Parameters
    ----------
    scheduler : str, distributed.Client or DaskSession
        See :func:`parse_scheduler`; ``"threads"`` makes the block run on
        this process's threads (also inside an outer ``use_scheduler``); a
        session yielded by an outer ``use_scheduler`` is made current again,
        with the data it has already sent.
    connect_timeout : float
        Seconds to wait for the scheduler at a ``tcp://`` address.

    Yields
    ------
    DaskSession or None
        The session (``.client``, ``.n_workers``, ``.stats``), None for threads.

    Raises
    ------
    SchedulerError
        A malformed ``scheduler``, or Dask not installed.
    SchedulerUnreachableError
        Nothing answers at the address.

    Examples
    --------
    >>> with use_scheduler("local:2") as session:          # doctest: +SKIP
    ...     red = pdvc.reduce_views(vol, vg, geom, proj)
    """
    from ._session import DaskSession

    if isinstance(scheduler, DaskSession):  # a session made current again: same cluster, same data sent
        token = _CURRENT.set(scheduler)
        try:
            yield scheduler
        finally:
            _CURRENT.reset(token)
        return
    spec = parse_scheduler(scheduler)
    if spec.kind == "threads":
        token = _CURRENT.set(None)
        try:
            yield None
        finally:
            _CURRENT.reset(token)
        return
    if not (isinstance(connect_timeout, (int, float)) and connect_timeout > 0):
        raise SchedulerError(f"connect_timeout must be a positive number of seconds, got {connect_timeout!r}")
    distributed = _import_distributed()
    cluster = None
    if spec.kind == "local":
        cluster, client = _start_local(spec, distributed)
        own = True
    elif spec.kind == "address":
        client, own = _connect(spec.address, float(connect_timeout), distributed), True
    else:
        client, own = spec.client, False
    session = DaskSession(client, spec)
    log.info("scheduler %s: %d worker(s), %d thread(s) in all", spec, session.n_workers, session.n_threads)
    token = _CURRENT.set(session)
    try:
        yield session
    finally:
        _CURRENT.reset(token)
        st = session.stats
        log.info(
            "scheduler %s: %d calls, %d tasks; sent %.1f MB, read from files %.1f MB, received %.1f MB; "
            "volume sent %d times, projections %d times; %d re-runs after lost workers",
            spec, st["calls"], st["tasks"], st["sent_bytes"] / 1e6, st["file_bytes"] / 1e6, st["received_bytes"] / 1e6,
            st["volume_sends"], st["projection_sends"], st["reruns"],
        )
        session.release()
        if own:
            client.close()
        if cluster is not None:
            cluster.close()


def scheduler_keyword(fn):
    """Give ``fn`` a keyword ``scheduler=None`` that runs the whole call inside :func:`use_scheduler`.

    ``scheduler=None`` (the default) keeps the scheduler current in the
    caller's context (threads when there is none); anything else is
    checked and made current for the call, and a local cluster it starts
    is closed when the call returns or raises.
    """

    @functools.wraps(fn)
    def wrapper(*args, scheduler=None, **kwargs):
        if scheduler is None:
            return fn(*args, **kwargs)
        with use_scheduler(scheduler):
            return fn(*args, **kwargs)

    sig = inspect.signature(fn)
    params = list(sig.parameters.values())
    extra = inspect.Parameter("scheduler", inspect.Parameter.KEYWORD_ONLY, default=None)
    at = next((i for i, p in enumerate(params) if p.kind is inspect.Parameter.VAR_KEYWORD), len(params))
    wrapper.__signature__ = sig.replace(parameters=params[:at] + [extra] + params[at:])
    return wrapper
