"""Progress bars: on a terminal the work done deep down shows, in a pipe nothing does."""

from __future__ import annotations

import io

import pytest

from twind import progress


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.mark.parametrize("stream", [Terminal(), io.StringIO()])
def test_a_bar_on_a_terminal_and_nothing_in_a_pipe(stream, monkeypatch) -> None:  # noqa: ANN001
    monkeypatch.setattr("sys.stderr", stream)
    progress.tick()  # no bar shown: nothing happens
    with progress.shown("twind fit", "evaluation"):
        for _ in range(7):
            progress.tick()
        progress.note("step 2: coil_imbalance")
        progress.tick()
    written = stream.getvalue()
    if stream.isatty():
        assert "twind fit" in written and "evaluation" in written
    else:
        assert written == ""
