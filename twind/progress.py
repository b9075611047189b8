"""Progress of long work: a bar (tqdm) on a terminal's stderr, nothing in a pipe or a log.

Work far down reports with :func:`tick` (a model evaluated, a Welch segment summed) and
:func:`note` (which hypothesis a diagnosis is on); the command that started it decides with
:func:`shown` whether anyone sees it. As with logging, nothing is passed down the calls, and
worker threads report to the same bar. While a bar is shown, what is printed goes above it.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, TextIO

from tqdm import tqdm

_bar: tqdm | None = None


class _Above:
    """Standard output while a bar is shown: whole lines are written above the bar."""

    def __init__(self, out: TextIO) -> None:
        self.out, self.pending = out, ""

    def write(self, text: str) -> int:
        lines, newline, self.pending = (self.pending + text).rpartition("\n")
        if newline:
            if _bar is not None:
                _bar.clear()
            self.out.write(lines + newline)
            self.out.flush()
            if _bar is not None:
                _bar.refresh()
        return len(text)

    def __getattr__(self, name: str) -> Any:  # noqa: ANN401 - flush, isatty, encoding, ...
        return getattr(self.out, name)


@contextmanager
def shown(label: str, unit: str = "it") -> Iterator[None]:
    """Show the work done inside the block as a bar labelled `label`, counting `unit`:
    on stderr when it is a terminal, not at all otherwise; gone when the block ends.

    Parameters
    ----------
    label : str
        What the bar is of, e.g. ``twind fit``.
    unit : str
        What one :func:`tick` counts, singular (the bar adds the plural ``s``).

    Yields
    ------
    None
    """
    global _bar
    outer, _bar = _bar, tqdm(desc=label, unit=f" {unit}s", file=sys.stderr, disable=None,
                             leave=False, mininterval=0.5, dynamic_ncols=True)
    out = sys.stdout
    above = None if _bar.disable or isinstance(out, _Above) else _Above(out)
    if above:
        sys.stdout = above
    try:
        yield
    finally:
        _bar.close()
        _bar = outer
        if above:
            sys.stdout = out
            out.write(above.pending)


def tick(n: int = 1) -> None:
    """Count `n` units of work on the bar shown, if any."""
    if _bar is not None:
        _bar.update(n)


def note(text: str) -> None:
    """Say on the bar shown, if any, what the work is on now."""
    if _bar is not None:
        _bar.set_postfix_str(text, refresh=False)
