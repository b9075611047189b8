"""The layers of docs/architecture.md hold: import-linter checks pyproject.toml's contracts
against every import in the package, those inside functions included; and imports stand at
the top of their module unless a comment says why not; functions are short enough to read at
once (100 lines at most), and modules short enough to hold one concept (800 lines)."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest
from importlinter.cli import lint_imports

from twind.cli.commands import COMMANDS
from twind.model.effects import CATALOGUE, CHANNEL_FILTERS, FAMILIES

ROOT = Path(__file__).resolve().parent.parent


def test_the_imports_keep_the_layers(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(ROOT)
    assert lint_imports(config_filename=str(ROOT / "pyproject.toml"), no_cache=True,
                        no_logo=True) == 0


def _imports_inside_functions() -> list[tuple[str, int, bool]]:
    """Every import statement inside a function: file, line, and whether a comment on its
    line or the one before says why it is there."""
    found = []
    for path in sorted((ROOT / "twind").rglob("*.py")):
        lines = path.read_text().splitlines()
        for node in ast.walk(ast.parse("\n".join(lines))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for inner in ast.walk(node):
                    if isinstance(inner, (ast.Import, ast.ImportFrom)):
                        here = lines[inner.lineno - 1] + lines[inner.lineno - 2]
                        found.append((str(path.relative_to(ROOT)), inner.lineno, "#" in here))
    return found


def test_imports_are_at_module_top_unless_a_comment_says_why() -> None:
    inside = _imports_inside_functions()
    print(f"{len(inside)} import(s) inside functions: {inside}")
    assert len(inside) < 20, inside
    assert all(said for _, _, said in inside), [i for i in inside if not i[2]]


def test_no_function_is_longer_than_a_screenful_or_two() -> None:
    long = [(str(path.relative_to(ROOT)), node.name, node.end_lineno - node.lineno + 1)
            for path in sorted((ROOT / "twind").rglob("*.py"))
            for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
            and node.end_lineno - node.lineno + 1 > 100]
    assert not long, long


MODULE_LINES = 800
"""The longest module a reader takes in as one concept."""


def test_no_module_is_longer_than_one_concept() -> None:
    sizes = {str(path.relative_to(ROOT)): len(path.read_text().splitlines())
             for path in sorted((ROOT / "twind").rglob("*.py"))}
    assert not {p: n for p, n in sizes.items() if n > MODULE_LINES}


INDEPENDENT = {Path("twind/model/effects.py"), Path("twind/commissioning/hidden.py"),
               Path("twind/commissioning/concealed.py")}
"""The catalogue's own module, and the effects put in by hand independently of it."""


def _branches_on_effect_names() -> list[tuple[str, int, str]]:
    """Comparisons with a catalogue entry's name (``effect == "bounce_roll"``, ``in (...)``)
    in the package's modules that use the catalogue, outside its own module, the proof
    harness and the effects put in by hand (whose independent physics knows each effect by
    name)."""
    names = {*CATALOGUE, *CHANNEL_FILTERS, *FAMILIES}
    found = []
    for path in sorted((ROOT / "twind").rglob("*.py")):
        rel = path.relative_to(ROOT)
        text = path.read_text()
        if rel.parts[1] == "lab" or rel in INDEPENDENT or "twind.model.effects" not in text:
            continue
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.Compare):
                for const in ast.walk(node):
                    if isinstance(const, ast.Constant) and const.value in names:
                        found.append((str(rel), node.lineno, const.value))
    return found


def test_an_effect_s_traits_are_its_fields_not_branches_on_its_name() -> None:
    found = _branches_on_effect_names()
    assert not found, f"branches on an effect's name outside twind/model/effects.py: {found}"


def test_only_cli_parses_a_command_line() -> None:
    """Domain functions take typed arguments: argparse is imported in cli/ alone."""
    outside = [str(p.relative_to(ROOT)) for p in sorted((ROOT / "twind").rglob("*.py"))
               if p.relative_to(ROOT).parts[1] != "cli" and any(
                   isinstance(n, (ast.Import, ast.ImportFrom)) and "argparse" in
                   ([a.name for a in n.names] if isinstance(n, ast.Import) else [n.module])
                   for n in ast.walk(ast.parse(p.read_text())))]
    assert not outside, f"modules outside cli/ that import argparse: {outside}"


def test_every_command_runs_a_function_of_cli() -> None:
    """Each command's run, named ``"module:function"`` so that it loads only when it runs,
    is a function of a module of ``twind/cli``: a misspelt one fails here, not in use."""
    commands = [c for top in COMMANDS for c in (top.subcommands or [top])]
    runs = [c.run.split(":") for c in commands]
    assert all(module.startswith("twind.cli.") for module, _ in runs), runs
    missing = [f"{module}:{name}" for module, name in runs
               if not callable(getattr(importlib.import_module(module), name, None))]
    assert not missing
