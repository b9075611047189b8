"""A page loaded in a real headless browser (Debian's Chromium, package ``chromium``), and
the tables read off a page.

Without it the tests that need it skip, saying how to get it; ``.ci/run`` installs it and
sets ``TWIND_REQUIRE_BROWSER=1``, under which a missing browser fails instead.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from html.parser import HTMLParser
from pathlib import Path

import pytest

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars"]
"""Headless, as root, with no network of its own (the machine's is closed)."""


def chromium() -> str:
    """The browser's executable; skips (fails under ``TWIND_REQUIRE_BROWSER``) without one."""
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if found:
        return found
    why = "no chromium on PATH (Debian: apt-get install chromium)"
    if os.environ.get("TWIND_REQUIRE_BROWSER"):
        pytest.fail(why)
    pytest.skip(why)


def load(page: Path, screenshot: Path | None = None, width: int = 1200,
         height: int = 2400) -> str:
    """The DOM of `page` as the browser built it; with `screenshot`, also a PNG of its first
    `width` x `height` pixels."""
    url = page.resolve().as_uri()
    with tempfile.TemporaryDirectory() as profile:
        run = [chromium(), *FLAGS, f"--user-data-dir={profile}"]
        if screenshot is not None:
            subprocess.run([*run, f"--window-size={width},{height}",
                            f"--screenshot={screenshot}", url], check=True, timeout=120,
                           capture_output=True)
        dom = subprocess.run([*run, "--dump-dom", url], check=True, timeout=120,
                             capture_output=True, text=True)
    return dom.stdout


class _Page(HTMLParser):
    """The text of each element with an id, tables row by row: ``{id: [[cell, ...], ...]}``."""

    def __init__(self) -> None:
        super().__init__()
        self.found: dict[str, list[list[str]]] = {}
        self._id: str | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        given = dict(attrs).get("id")
        if given:
            self._id = given
            self.found[given] = [] if tag == "table" else [[""]]
        elif tag == "tr" and self._id:
            self.found[self._id].append([])
        elif tag in ("td", "th") and self._id:
            self.found[self._id][-1].append("")

    def handle_endtag(self, tag: str) -> None:
        if tag in ("table", "p"):
            self._id = None

    def handle_data(self, data: str) -> None:
        if self._id and self.found[self._id] and self.found[self._id][-1]:
            self.found[self._id][-1][-1] += data


def tables(page: str) -> dict[str, list[list[str]]]:
    """The text of each element of `page` with an id, tables row by row."""
    parser = _Page()
    parser.feed(page)
    return parser.found
