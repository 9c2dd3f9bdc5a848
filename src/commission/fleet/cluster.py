"""The logs' identifications as Dask tasks, on a local cluster or an existing one.

One task per log: it takes the log's path (the workers read the logs themselves, so every worker
must see the same paths: a shared folder on a cluster) and returns its row. What happens when a
task cannot finish is Dask's own retry machinery, set to one retry:

- the task raises an unexpected error (not a :class:`CommissionError`): ``Client.map(retries=1)``;
- the worker process dies on it (a crash, killed for memory): the scheduler moves the task to
  another worker until it has killed ``distributed.scheduler.allowed-failures`` + 1 of them.

The scheduler blames a death on every task the dead worker held, running or waiting, so the
local cluster sends a worker only the task it runs (``distributed.scheduler.worker-saturation``
1.0; it applies when the batch has more logs than twice the workers' threads, Dask's queuing
rule) and allows one failure. An existing cluster keeps its scheduler's settings (Dask's
defaults: 3 failures, saturation 1.1); start it with ``DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES=1``
and ``DASK_DISTRIBUTED__SCHEDULER__WORKER_SATURATION=1.0`` for the same policy. Either way the log
then becomes a ``crashed`` row and the batch goes on.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from ..exceptions import CommissionError

__all__ = ["ClusterError", "ClusterInfo", "Task", "connect", "identify_all"]

#: A task: ``task(source path, content SHA-256, options=identification options as a mapping)`` → row.
Task = Callable[..., dict[str, Any]]

#: How long to wait for a scheduler to answer [s] (Dask retries a refused connection until then).
CONNECT_TIMEOUT_S = 10.0
#: How long to wait for the scheduler to have a worker [s] (a cluster's workers may be starting).
WORKERS_TIMEOUT_S = 30.0
#: How long logs may wait on a cluster that has lost every worker before the run stops [s] (Dask
#: would keep them waiting for ever; a local cluster's nanny restarts a dead worker within seconds).
NO_WORKERS_S = 60.0
#: How often a run with nothing finished asks the scheduler for its workers [s].
WORKERS_POLL_S = 2.0


class ClusterError(CommissionError):
    """The Dask scheduler cannot be reached, or has no workers."""


@dataclass(frozen=True)
class ClusterInfo:
    """Where the tasks ran."""

    scheduler: str
    """The scheduler's address (a local cluster's too)."""
    local: bool
    """True for the local cluster this run started."""
    workers: int
    threads: int
    """Task slots: the workers' threads summed."""


@contextlib.contextmanager
def connect(scheduler: str | None, workers: int | None = None) -> Iterator[tuple[Any, ClusterInfo]]:
    """A Dask client: to the scheduler at ``scheduler`` (``tcp://HOST:PORT``), or to a local
    cluster of ``workers`` processes (default: one per core) with one thread each, on loopback.
    Closed (and the local cluster stopped) on exit."""
    import dask
    from dask.system import CPU_COUNT
    from distributed import Client, LocalCluster

    cluster = None
    try:
        if scheduler is None:
            with dask.config.set({"distributed.scheduler.allowed-failures": 1,
                                  "distributed.scheduler.worker-saturation": 1.0}):
                # processes, not threads: the identifier holds the GIL in its Python stages
                # no dashboard, and its HTTP server on a free loopback port (not 8787, perhaps taken)
                cluster = LocalCluster(n_workers=workers or CPU_COUNT, threads_per_worker=1, processes=True,
                                       host="127.0.0.1", silence_logs=logging.ERROR,
                                       scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"})
            client = Client(cluster)
        else:
            try:
                client = Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
            except (OSError, TimeoutError, ValueError) as err:
                raise ClusterError(f"cannot reach the Dask scheduler at {scheduler}: {err}") from err
    except BaseException:
        if cluster is not None:
            cluster.close()
        raise
    try:
        try:
            client.wait_for_workers(1, timeout=WORKERS_TIMEOUT_S)
        except TimeoutError as err:
            raise ClusterError(f"the Dask scheduler at {scheduler} has no workers "
                               f"(waited {WORKERS_TIMEOUT_S:g} s)") from err
        info = client.scheduler_info()
        found = info.get("workers", {})
        yield client, ClusterInfo(scheduler=str(info.get("address", scheduler)), local=cluster is not None,
                                  workers=len(found), threads=sum(int(w.get("nthreads", 1)) for w in found.values()))
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def identify_all(client: Any, logs: Sequence[tuple[str, str]], options: Mapping[str, Any], task: Task,
                 on_row: Callable[[dict[str, Any]], None]) -> None:
    """Run ``task`` on every (source, digest) of ``logs`` and hand each row to ``on_row`` as it
    comes (in completion order); a task that could not finish gives a ``crashed`` row."""
    from distributed import as_completed

    from .table import crashed_row

    batch = uuid.uuid4().hex[:8]
    # one map, so the scheduler sees the whole batch at once and queues it (module docstring); keys
    # readable (the dashboard shows them) and unique per run, so a re-run never meets an old result
    keys = [f"identify-{digest[:12]}-{batch}" for _, digest in logs]
    submitted = client.map(task, [s for s, _ in logs], [d for _, d in logs], key=keys, options=dict(options),
                           pure=False, retries=1)
    futures = dict(zip(submitted, logs))
    finished = as_completed(futures)
    watch = _WorkerWatch(client)
    while not finished.is_empty():
        batch = finished.next_batch(block=False)
        if not batch:
            watch.check(len(futures))
            time.sleep(0.05)
            continue
        for future in batch:
            source, digest = futures.pop(future)
            try:
                row = future.result()
            except Exception as err:  # noqa: BLE001 — any failure of one task (KilledWorker too) is that log's row
                row = crashed_row(source, digest, _crash_text(err))
            finally:
                future.release()
            on_row(row)


class _WorkerWatch:
    """Raises ClusterError once the scheduler has had no worker for ``NO_WORKERS_S``."""

    def __init__(self, client: Any) -> None:
        self.client = client
        self.asked = -math.inf
        self.alone_since: float | None = None

    def check(self, waiting: int) -> None:
        now = time.monotonic()
        if now - self.asked < WORKERS_POLL_S:
            return
        self.asked = now
        if self.client.nthreads():
            self.alone_since = None
            return
        if self.alone_since is None:
            self.alone_since = now
        elif now - self.alone_since >= NO_WORKERS_S:
            raise ClusterError(f"the Dask cluster has had no workers for {now - self.alone_since:.0f} s, with "
                               f"{waiting} log(s) waiting; the logs identified so far are kept: start workers "
                               "and run again to identify the rest")


def _crash_text(err: BaseException) -> str:
    from distributed.scheduler import KilledWorker

    if isinstance(err, KilledWorker):
        return "the worker died on this log, also when it was tried again"
    return f"{type(err).__name__}: {err} (also when it was tried again)"
