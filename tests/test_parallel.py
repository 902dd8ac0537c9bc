"""`reconstruction._parallel`: results in the items' order, never more than `ahead` of them waiting."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from reconstruction._parallel import ordered_ahead


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
