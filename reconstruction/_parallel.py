"""Spreading independent work over the CPU cores this process may use, without changing any result."""

from __future__ import annotations

import collections
import os
import queue
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity mask on Linux, else all of them), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def ordered_ahead(pool: ThreadPoolExecutor, fn: Callable[[T], R], items: Iterable[T], ahead: int) -> Iterator[R]:
    """``fn`` of each item, in the items' order, with up to ``ahead`` of them computed in ``pool`` before they are
    asked for: work whose results are consumed one by one (and in order) keeps the other cores busy, and no more
    than ``ahead`` results wait in memory. An exception is raised where its item's result would have come."""
    pending: collections.deque[Future[R]] = collections.deque()
    for item in items:
        pending.append(pool.submit(fn, item))
        if len(pending) > ahead:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()


class _Stopped(Exception):
    """Raised by a job's ``tick`` once the run is stopping (another job failed, or Ctrl-C): ends the job early."""


def run_jobs_reporting(
    jobs: Sequence[Callable[[Callable[[int], None]], None]], workers: int, report: Callable[[int], None]
) -> None:
    """Runs ``jobs`` on ``workers`` threads, reporting progress from the calling thread.

    Each job is called with ``tick(n)``, to call whenever it has finished ``n`` more units of work; ``report(done)``
    gets the running total, in the calling thread (a progress bar need not be thread-safe). A job made of several
    steps (one C++ call each) calls ``tick`` between them. When a job fails or the caller is interrupted (Ctrl-C,
    SIGTERM), jobs not yet started are cancelled and running ones stop at their next ``tick``, so the run ends after
    at most one step of each running job, not after all of them; the first error is raised.
    """
    events: queue.SimpleQueue[int] = queue.SimpleQueue()
    stopping = threading.Event()

    def tick(units: int) -> None:
        events.put(units)
        if stopping.is_set():
            raise _Stopped

    done = 0
    with ThreadPoolExecutor(max(1, workers)) as pool:
        futures = [pool.submit(job, tick) for job in jobs]
        try:
            while True:
                finished = all(f.done() for f in futures)  # read before draining: no tick can come after it
                try:
                    units = events.get(timeout=0.1) if not finished else events.get_nowait()
                    while True:  # what has come meanwhile, then back to checking the jobs
                        done += units
                        report(done)
                        units = events.get_nowait()
                except queue.Empty:
                    pass
                failed = next((f for f in futures if f.done() and f.exception() is not None), None)
                if failed is not None:
                    raise failed.exception()  # type: ignore[misc]
                if finished:
                    break
        except BaseException:
            stopping.set()
            for future in futures:
                future.cancel()
            raise
