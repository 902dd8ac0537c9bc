"""`reconstruction._parallel`: results in the items' order, never more than `ahead` of them waiting."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import pytest

from reconstruction._parallel import ordered_ahead, run_jobs_reporting


def test_ordered_ahead_keeps_order_and_bounds_what_waits() -> None:
    """Later items finish first (they sleep less), yet come out in order; while the consumer holds one result,
    at most `ahead` more have been handed to the pool."""
    started: list[int] = []
    lock = threading.Lock()

    def work(i: int) -> int:
        with lock:
            started.append(i)
        time.sleep(0.002 * (10 - i))
        return i * i

    out = []
    with ThreadPoolExecutor(3) as pool:
        for value in ordered_ahead(pool, work, range(10), ahead=2):
            out.append(value)
            with lock:
                assert len(started) <= len(out) + 2  # the one consumed, plus `ahead` in flight
    assert out == [i * i for i in range(10)]


def test_ordered_ahead_raises_where_the_failing_item_would_have_come() -> None:
    def work(i: int) -> int:
        if i == 3:
            raise ValueError("item 3")
        return i

    got = []
    with ThreadPoolExecutor(2) as pool, pytest.raises(ValueError, match="item 3"):
        for value in ordered_ahead(pool, work, range(6), ahead=2):
            got.append(value)
    assert got == [0, 1, 2]


def test_jobs_report_their_progress_in_the_calling_thread() -> None:
    """Every unit ticked is counted, the totals rise to the sum, and `report` runs in the caller's thread (a
    progress bar need not be thread-safe)."""
    caller = threading.get_ident()
    seen: list[tuple[int, int]] = []

    def job(steps: int) -> Callable[[Callable[[int], None]], None]:
        def run(tick: Callable[[int], None]) -> None:
            for _ in range(steps):
                time.sleep(0.005)
                tick(2)

        return run

    run_jobs_reporting([job(n) for n in (3, 1, 4, 2)], 2, lambda done: seen.append((done, threading.get_ident())))
    totals = [done for done, _ in seen]
    assert totals == sorted(totals) and totals[-1] == 2 * (3 + 1 + 4 + 2)
    assert {ident for _, ident in seen} == {caller}


def test_a_failing_job_stops_the_others_at_their_next_step() -> None:
    """The first error is raised; jobs not started are cancelled and running ones end at their next tick, rather
    than every job running to its end (a Ctrl-C after 30 s of SIFT)."""
    steps_run: list[int] = []
    lock = threading.Lock()

    def long_job(i: int) -> Callable[[Callable[[int], None]], None]:
        def run(tick: Callable[[int], None]) -> None:
            for _ in range(100):
                time.sleep(0.01)
                with lock:
                    steps_run.append(i)
                tick(1)

        return run

    def failing(tick: Callable[[int], None]) -> None:
        time.sleep(0.05)
        raise ValueError("chunk 1 failed")

    tick = time.perf_counter()
    with pytest.raises(ValueError, match="chunk 1 failed"):
        run_jobs_reporting([long_job(0), failing, long_job(2), long_job(3)], 2, lambda _done: None)
    assert time.perf_counter() - tick < 0.5  # not the 1 s of a long job, let alone 3 of them
    assert 3 not in steps_run  # never started: cancelled
