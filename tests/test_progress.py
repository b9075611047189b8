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


@pytest.mark.parametrize("stream", [Terminal(), io.StringIO()])
def test_lines_printed_during_a_bar_reach_stdout_whole(stream, monkeypatch, capsys) -> None:  # noqa: ANN001
    monkeypatch.setattr("sys.stderr", stream)
    with progress.shown("twind bench", "optic"):
        progress.tick()
        print("optic 1: frequencies", end=" ")
        print("within 0.010 mHz", flush=True)
        progress.tick()
        print("worst of 1", end="")
    print("; done")
    assert capsys.readouterr().out == "optic 1: frequencies within 0.010 mHz\nworst of 1; done\n"
    assert "optic 1" not in stream.getvalue()
