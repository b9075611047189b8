"""A starting configuration of an optic twind does not ship, written from its state-space
model's input and output names by a site's naming rules (:mod:`twind.config.naming`).

:func:`draft_config` maps every model input a rule names to its excitation point, every
output to its readback, the collocated pairs that label the modes, and the damping loops the
rules close (their controllers twind's, as the shipped KAGRA files have them), each entry with
a comment naming the model's signal and the rule that made it; it lists what no rule maps,
and for each drive with a collocated readback the model's response there at
:data:`DC_HZ`, which a person checks: KAGRA's models normalise each excitation by its local
sensor at DC, so a right pairing reads a positive number of order one.
:func:`write_config` writes it beside nothing (the model file is named relative to the
configuration, never copied), refuses to overwrite and reads the file back.
"""

from __future__ import annotations

import json
import os
import re
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twind import __version__
from twind.config import load_config
from twind.config.naming import (
    SITES,
    Entry,
    Naming,
    default_naming,
    load_naming,
    shipped_namings,
)
from twind.errors import TwindError
from twind.model.statespace import StateSpace, read_mat

DC_HZ = 1e-3
"""Where the DC check evaluates the model: its free masses make 0 Hz singular, and the
shipped models' collocated responses are flat to 0.1 % from 1e-4 Hz to here."""
BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


@dataclass(frozen=True)
class DCCheck:
    """A drive, its collocated readback, and the model's response between them at
    :data:`DC_HZ` (real part; the imaginary part is below 1e-3 of it in the shipped models)."""

    drive: str
    readback: str
    input: str
    output: str
    response: float


@dataclass(frozen=True)
class Draft:
    """A starting configuration, as text and as what it maps.

    Attributes
    ----------
    optic : str
    text : str
        The TOML file.
    drives, readbacks, shapes : dict of str to Entry
        By test point (or label): the entry the rules made.
    loops : dict of str to str
        Each damping loop's module and the model input its OUT drives.
    checks : tuple of DCCheck
    unmapped_inputs, unmapped_outputs : tuple of str
        The model's signals no table names.
    naming : Naming
    """

    optic: str
    text: str
    drives: Mapping[str, Entry]
    readbacks: Mapping[str, Entry]
    shapes: Mapping[str, Entry]
    loops: Mapping[str, str]
    checks: tuple[DCCheck, ...]
    unmapped_inputs: tuple[str, ...]
    unmapped_outputs: tuple[str, ...]
    naming: Naming


def draft_config(model_file: str | Path, optic: str, output: str | Path, *,
                 naming: str | Path | None = None, ifo: str | None = None,
                 system: str | None = None) -> Draft:
    """The configuration of `optic` whose plant is the model in `model_file`, as it would be
    written to `output` (the model named relative to it).

    Parameters
    ----------
    model_file : path
        A ``.mat`` state-space model (:func:`~twind.model.statespace.read_mat`).
    optic : str
        The optic's name in its channels (letters and digits), e.g. ``PR3``.
    output : path
        The configuration file to be.
    naming : path, optional
        A naming table; by default the one twind ships for `ifo` (or its only one).
    ifo, system : str, optional
        The channels' prefix; by default the naming table's.

    Returns
    -------
    Draft

    Raises
    ------
    TwindError
        A name that is not letters and digits, no naming table for the ifo, a model no rule
        maps a drive or a readback of.
    """
    for what, value in (("--optic", optic), ("--ifo", ifo), ("--system", system)):
        if value is not None and not (value.isascii() and value.isalnum()):
            raise TwindError(f"{what} {value!r}: a channel name's part is letters and digits")
    rules = _naming(naming, ifo)
    model = read_mat(model_file)
    ifo, system = ifo or rules.ifo, system or rules.system
    drives = {e.point: e for e in rules.entries("drives", model)}
    readbacks = {e.point: e for e in rules.entries("readbacks", model)}
    if not drives or not readbacks:
        kind = "input" if not drives else "output"
        msg = (f"{model_file}: no rule of {_shown(rules.source)} names a model {kind} "
               f"(its {kind}s: {', '.join(_short(_names(model, kind))[:8])} ...); give "
               "--naming FILE with rules for this model's names (the shipped table shows "
               "the form)")
        raise TwindError(msg)
    shapes = {e.point: e for e in rules.entries("shapes", model)}
    loops = _loops(rules, model, drives, readbacks)
    unmapped = _unmapped(model, drives, readbacks, shapes)
    text = _text(optic, ifo, system, Path(model_file), Path(output), naming, rules,
                 (drives, readbacks, shapes, loops), model) + _unmapped_text(*unmapped, rules)
    return Draft(optic, text, drives, readbacks, shapes,
                 {m: drives[d].names["input"] for m, (_, d) in loops.items()},
                 _checks(rules, model, drives, readbacks), *unmapped, rules)


def write_config(model_file: str | Path, optic: str, output: str | Path, **options: str | None
                 ) -> Draft:
    """:func:`draft_config`, written to `output` (never over a file) and read back with
    :func:`~twind.config.load_config` (a file that does not load is removed, and its error
    raised)."""
    output = Path(output)
    if output.exists():
        raise TwindError(f"{output} exists; twind does not overwrite a configuration")
    draft = draft_config(model_file, optic, output, **options)
    with output.open("x") as f:
        f.write(draft.text)
    try:
        load_config(output)
    except TwindError:
        output.unlink()
        raise
    return draft


def _naming(path: str | Path | None, ifo: str | None) -> Naming:
    """The naming table at `path`, else the shipped one for `ifo`, else the only shipped one."""
    if path is not None:
        if not Path(path).is_file():
            raise TwindError(f"--naming {path}: no such file")
        return load_naming(Path(path))
    if ifo is not None:
        found = default_naming(ifo)
        if found is None:
            msg = (f"--ifo {ifo}: twind ships no naming table for it; give --naming FILE "
                   "(twind/configs/kagra/naming.toml shows the form)")
            raise TwindError(msg)
        return found
    shipped = shipped_namings()
    if len(shipped) != 1:
        raise TwindError("give --ifo or --naming: twind ships several naming tables")
    return shipped[0]


def _loops(rules: Naming, model: StateSpace, drives: Mapping[str, Entry],
           readbacks: Mapping[str, Entry]) -> dict[str, tuple[Entry, str]]:
    """The damping loops whose IN1 is a readback and whose drive point is mapped: each
    module's entry and drive point."""
    loops = {}
    for entry in rules.entries("damping", model):
        drive = entry.rule.extra["drive"].format(**entry.words)
        if f"{entry.point}_IN1" in readbacks and drive in drives:
            loops[entry.point] = (entry, drive)
    return loops


def _checks(rules: Naming, model: StateSpace, drives: Mapping[str, Entry],
            readbacks: Mapping[str, Entry]) -> tuple[DCCheck, ...]:
    """Each drive with a collocated readback, and the model's response between them."""
    local = {e.names["input"]: e.names["output"] for e in rules.entries("collocated", model)}
    by_output = {}
    for point, e in readbacks.items():
        by_output.setdefault(e.names["output"], point)
    pairs = [(d, by_output[local[e.names["input"]]]) for d, e in drives.items()
             if local.get(e.names["input"]) in by_output]
    if not pairs:
        return ()
    ins = [drives[d].names["input"] for d, _ in pairs]
    outs = [readbacks[r].names["output"] for _, r in pairs]
    h = model.response(np.array([DC_HZ]), ins, outs)[0]
    return tuple(DCCheck(d, r, i, o, float(h[k, k].real))
                 for k, ((d, r), i, o) in enumerate(zip(pairs, ins, outs, strict=True)))


def _unmapped(model: StateSpace, drives: Mapping[str, Entry], readbacks: Mapping[str, Entry],
              shapes: Mapping[str, Entry]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The model's inputs and outputs (short names) that no drive, readback or shape uses."""
    used = {n for table in (drives, readbacks, shapes) for e in table.values()
            for n in e.names.values()}
    return (tuple(n for n in _short(model.inputs) if n not in used),
            tuple(n for n in _short(model.outputs) if n not in used))


def _names(model: StateSpace, kind: str) -> tuple[str, ...]:
    return model.inputs if kind == "input" else model.outputs


def _short(names: Sequence[str]) -> list[str]:
    return [n.rsplit("/", 1)[-1] for n in names]


def _shown(path: str | Path) -> str:
    """A naming table's path as a message shows it: from the package's root if shipped."""
    path = Path(path).resolve()
    return str(path.relative_to(SITES.parent.parent)) if path.is_relative_to(SITES) else str(path)


# ------------------------------------------------------------------------------ the text
def _text(optic: str, ifo: str, system: str, model_file: Path, output: Path,
          naming: str | Path | None, rules: Naming, tables: tuple, model: StateSpace) -> str:
    """The configuration file."""
    drives, readbacks, shapes, loops = tables
    full = {n.rsplit("/", 1)[-1]: n for n in (*model.inputs, *model.outputs)}
    parts = [_head(optic, model_file, output, rules),
             f'[optic]\nname = "{optic}"\nmodel = "statespace"\n',
             _channels(ifo, system, optic, naming, output),
             _statespace(model_file, output, rules),
             _table("statespace.shapes", "a DOF and a collocated model input and output: each "
                    "mode is labelled by the DOF carrying the largest share of its inverse "
                    "mass there (twind.model.statespace)",
                    {k: [e.names["input"], e.names["output"]] for k, e in shapes.items()},
                    shapes, full),
             _table("drives", "excitation test points (<suffix>_EXC): the model input each "
                    "drives", {k: e.names["input"] for k, e in drives.items()}, drives, full),
             _table("readbacks", "channels that read the suspension: the model output each "
                    "reads", {k: e.names["output"] for k, e in readbacks.items()}, readbacks,
                    full)]
    if loops:
        parts.append(_loops_text(loops, drives))
    return "\n".join(parts)


def _head(optic: str, model_file: Path, output: Path, rules: Naming) -> str:
    text = (f"{optic}: a starting configuration `twind model config` (twind {__version__}) "
            f"wrote from the state-space model {model_file.name}, its names mapped by "
            f"{rules.site}'s naming ({_shown(rules.source)}). Each entry's comment names the "
            "model's signal and the rule that made it: check them against the site's channel "
            f"list. `twind model response --config {output.name}` draws the model and labels "
            "its modes.")
    return _comment(text) + "\n"


def _channels(ifo: str, system: str, optic: str, naming: str | Path | None, output: Path
              ) -> str:
    lines = [f"[channels]  # {ifo}:{system}-{optic}_<suffix>", f"ifo = {_value(ifo)}",
             f"system = {_value(system)}"]
    shipped = default_naming(ifo)
    if naming is not None and (shipped is None or Path(shipped.source).resolve()
                               != Path(naming).resolve()):
        lines.append(f"naming = {_value(_relative(Path(naming), output))}  # the naming rules")
    return "\n".join(lines) + "\n"


def _statespace(model_file: Path, output: Path, rules: Naming) -> str:
    return "\n".join([
        "[statespace]",
        f"file = {_value(_relative(model_file, output))}  # relative to this file",
        f"source = {_value(f'{model_file.name}: give where the model comes from')}",
        f"rate = {_value(rules.rate)}  # {rules.site}'s front end (its naming table)", ""])


def _table(name: str, about: str, values: Mapping[str, object], entries: Mapping[str, Entry],
           full: Mapping[str, str]) -> str:
    """One table, each line commented with the model's full names and the rule."""
    lines = [_comment(about), f"[{name}]"]
    for key, value in values.items():
        e = entries[key]
        signals = ", ".join(full.get(n, n) for n in e.names.values())
        lines.append(f"{_key(key)} = {_value(value)}  # {signals}: {e.rule.text()}")
    return "\n".join(lines) + "\n"


def _loops_text(loops: Mapping[str, tuple[Entry, str]], drives: Mapping[str, Entry]) -> str:
    notes = dict.fromkeys(e.rule.extra.get("note", "") for e, _ in loops.values())
    parts = [_comment(" ".join(n for n in notes if n))]
    for module, (e, drive) in loops.items():
        lines = [f"[damping.{module}]  # IN1 {module}_IN1; OUT drives as {drive} does "
                 f"(rule {e.rule.point}: {e.rule.extra['drive']})",
                 f"drive = {_value(drives[drive].names['input'])}"]
        lines += [f"{k} = {_value(v)}" for k, v in e.rule.extra.items()
                  if k not in ("drive", "note")]
        parts.append("\n".join(lines))
    return "\n".join(parts) + "\n"


def _unmapped_text(ins: Sequence[str], outs: Sequence[str], rules: Naming) -> str:
    text = (f"Not mapped by any rule of {rules.site}'s naming: inputs "
            f"{', '.join(ins) or 'none'}; outputs {', '.join(outs) or 'none'}.")
    return "\n" + _comment(text) + "\n"


def _comment(text: str) -> str:
    return "\n".join(f"# {line}" for line in textwrap.wrap(text, 92))


def _relative(path: Path, output: Path) -> str:
    """`path` as a configuration at `output` names it: relative to its folder."""
    return Path(os.path.relpath(path.resolve(), output.resolve().parent)).as_posix()


def _key(key: str) -> str:
    return key if BARE_KEY.match(key) else json.dumps(key)


def _value(v: object) -> str:
    """A TOML value (strings as basic strings, whose escapes are JSON's)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    return json.dumps(str(v), ensure_ascii=False)
