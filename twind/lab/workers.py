"""Processes side by side for the lab's many-case runs (rates, pull tests).

Each worker runs on one thread: two workers that each spread their BLAS calls and the
engine's steps over both cores of a two-core machine wait on each other, and measured no
faster than one worker (4 nulls of :func:`~twind.lab.rates.nulls`, timed by hand: 23 s
against 21.6 s; 14 s with one thread each).
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager

import numba as nb
from threadpoolctl import threadpool_limits


@contextmanager
def side_by_side(workers: int) -> Iterator[Callable]:
    """A ``map`` over `workers` processes, each on one thread; the builtin ``map`` for one.

    Parameters
    ----------
    workers : int
        Processes.

    Yields
    ------
    callable
        ``map(function, iterable)``, results in order.
    """
    if workers <= 1:
        yield map
        return
    # spawned, not forked: numba's OpenMP threads do not survive a fork
    spawn = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, mp_context=spawn, initializer=_one_thread) as pool:
        yield pool.map


def _one_thread() -> None:
    """A worker's BLAS, OpenMP and numba on one thread."""
    threadpool_limits(limits=1)
    nb.set_num_threads(1)
