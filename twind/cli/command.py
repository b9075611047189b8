"""How a ``twind`` command is declared: its name, its help, its arguments and where its run
lives. The run is imported when the command runs, so that ``twind --help`` and the quick
commands (``status``, ``inject``) load none of the numerical stack."""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Command:
    """One subcommand of ``twind``.

    Attributes
    ----------
    name : str
        As typed: ``twind NAME``.
    help : str
        One line for ``twind --help``.
    arguments : callable
        Declares the command's arguments on its parser.
    run : str
        ``"module:function"``: the function that runs it, taking the parsed arguments and
        returning the exit status.
    progress : callable, optional
        The unit a progress bar counts for these arguments (None: no bar).
    subcommands : sequence of Command
        A command made of several (``twind model response``); then `run` is unused.
    """

    name: str
    help: str
    arguments: Callable[[argparse.ArgumentParser], None] = lambda parser: None
    run: str = ""
    progress: Callable[[argparse.Namespace], str | None] = lambda args: None
    subcommands: Sequence[Command] = field(default_factory=tuple)

    def add_to(self, sub: argparse._SubParsersAction) -> None:
        """Add this command (and its subcommands) to the subparsers `sub`."""
        parser = sub.add_parser(self.name, help=self.help, formatter_class=DefaultsShown)
        if self.subcommands:
            inner = parser.add_subparsers(dest=f"{self.name}_command", required=True)
            for command in self.subcommands:
                command.add_to(inner)
            return
        self.arguments(parser)
        parser.set_defaults(command_of=self)

    def __call__(self, args: argparse.Namespace) -> int:
        """Run the command on its parsed arguments."""
        module, function = self.run.split(":")
        return getattr(importlib.import_module(module), function)(args)


class DefaultsShown(argparse.HelpFormatter):
    """Help that ends each option's text with its default, where it has one to say (not
    None, a flag's or an empty list) and the text does not give it already."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (default is None or isinstance(default, bool) or default == []
                or default is argparse.SUPPRESS or "default" in text):
            return text
        return f"{text} (default: %(default)s)"


def counting(unit: str) -> Callable[[argparse.Namespace], str]:
    """A command's progress: a bar counting `unit` whatever its arguments."""
    return lambda args: unit
