"""The ``twind`` command line (:mod:`twind.cli.commands` declares every command).

Every user error (bad configuration, foton syntax, unknown optic, a file that is not a
recording, no twin running) ends as one line on stderr naming the input and the problem,
and exit status 2; never a traceback.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from collections.abc import Sequence
from contextlib import nullcontext

from twind import __version__, progress
from twind.bus.session import zenoh_message
from twind.cli.commands import COMMANDS
from twind.errors import TwindError, TwindWarning
from twind.loop import FOTON_READERS, FOTON_VARIABLE

_DEFAULT_SHOWWARNING = warnings.showwarning


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
    """twind's own warnings in one line for a person; the rest as Python shows them."""
    if issubclass(category, TwindWarning):
        print(f"twind: warning: {message}", file=sys.stderr)
    else:
        _DEFAULT_SHOWWARNING(message, category, filename, lineno, file, line)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every command."""
    p = argparse.ArgumentParser(
        prog="twind", description="twind: a digital twin of the LIGO 40m's suspended optics. "
                                  "'twind COMMAND --help' tells a command's options.")
    p.add_argument("--version", action="version", version=f"twind {__version__}")
    p.add_argument("--foton", choices=FOTON_READERS,
                   help="whose foton turns design strings into filters: twind's own (default) "
                        "or LIGO's python-foton (pip install 'twind[foton]')")
    sub = p.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_to(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``twind`` console script."""
    args = build_parser().parse_args(argv)
    if args.foton:  # in the environment, so that the processes a command starts read it too
        os.environ[FOTON_VARIABLE] = args.foton
    command = args.command_of
    unit = command.progress(args)
    try:
        with warnings.catch_warnings(), \
                progress.shown(f"twind {args.command}", unit) if unit else nullcontext():
            warnings.showwarning = _show_warning
            return command(args)
    except (TwindError, OSError) as err:
        print(f"twind: error: {err}", file=sys.stderr)
        return 2
    except Exception as err:
        if type(err).__module__.startswith("zenoh"):  # e.g. an endpoint that cannot be bound
            print(f"twind: error: {zenoh_message(err)}", file=sys.stderr)
            return 2
        raise
    except KeyboardInterrupt:
        return 130
