"""A site's naming as rules: from a test point's suffix to the name a state-space model gives
the signal there, read from a TOML table shipped beside the site's configurations
(``twind/configs/kagra/naming.toml``).

A rule is templates with ``{field}`` placeholders; each field is a list of words (the same in
a test point and in the model) or a table (the test point's word = the model's, e.g. the
optical lever's ``PIT = "P"``)::

    [fields]
    stage = ["IM", "TM"]
    dof = ["L", "T", "V", "R", "P", "Y"]

    [[drives]]                      # an excitation point (less _EXC) and the model input
    point = "{stage}_TEST_{dof}"
    input = ["exc_{stage}{dof}"]    # candidates: the first the model has wins

    [[readbacks]]                   # a channel's suffix and the model output
    point = "{stage}_DAMP_{dof}_IN1"
    output = ["OSEM_{stage}{dof}", "LVDT_{stage}{dof}"]

``[[shapes]]`` (``label``, ``input``, ``output``) names the DOFs that label the modes,
``[[collocated]]`` (``input``, ``output``) an excitation and its local sensor, and
``[[damping]]`` (``module``, ``drive`` and a controller) the loops a starting configuration
closes. The rules are the site's data; this module only substitutes words into templates, so
another site's naming is another table, not other code.
"""

from __future__ import annotations

import functools
import itertools
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from twind.config.reader import Reader, read_toml
from twind.errors import ConfigError, TwindWarning
from twind.model.statespace import StateSpace

SITES = Path(__file__).resolve().parent.parent / "configs"
"""Where the shipped sites' folders are, each with its naming table (``naming.toml``) if it
has one."""
NAMING_FILE = "naming.toml"
FIELD = re.compile(r"\{(\w+)\}")
KINDS = {"drives": ("point", ("input",)), "readbacks": ("point", ("output",)),
         "shapes": ("label", ("input", "output")), "collocated": ("", ("input", "output")),
         "damping": ("module", ())}
"""Each array of rules: the key of its site-side template ("" for none) and its model-side
candidate lists."""


class UnmappedReadbackWarning(TwindWarning):
    """A file holds a readback of the optic that its configuration does not map (left out)."""


@dataclass(frozen=True)
class Rule:
    """One rule of a naming table.

    Attributes
    ----------
    point : str
        The site-side template: a test point's suffix, a shape's label or a loop's module
        ("" for a collocated pair).
    sides : mapping of str to tuple of str
        ``input`` and/or ``output``: the model-side candidate templates, in order.
    extra : mapping of str to object
        The rule's other keys (a damping loop's ``drive`` template and controller).
    """

    point: str
    sides: Mapping[str, tuple[str, ...]]
    extra: Mapping[str, Any] = field(default_factory=dict)

    def fields(self) -> list[str]:
        """The fields the rule's templates use, in order of first use."""
        text = " ".join([self.point, *itertools.chain(*self.sides.values()),
                         str(self.extra.get("drive", ""))])
        return list(dict.fromkeys(FIELD.findall(text)))

    def text(self) -> str:
        """The rule as one line, e.g. ``{stage}_TEST_{dof} = exc_{stage}{dof}``."""
        model = ", ".join("|".join(c) for c in self.sides.values())
        return f"{self.point} = {model}" if self.point else model


@dataclass(frozen=True)
class Entry:
    """What one rule makes for one choice of its fields' words.

    Attributes
    ----------
    point : str
        The site-side name (a suffix, a label, a module).
    names : mapping of str to str
        ``input`` and/or ``output``: the model's names, as a configuration writes them.
    rule : Rule
    words : mapping of str to str
        Each field's site-side word.
    """

    point: str
    names: Mapping[str, str]
    rule: Rule
    words: Mapping[str, str]


@dataclass(frozen=True)
class Naming:
    """A site's naming table (module docstring).

    Attributes
    ----------
    site : str
        Whose naming it is, for messages (``KAGRA``).
    ifo, system : str
        The channels' prefix the site uses (``K1``, ``VIS``).
    rate : str
        The front end's rate, as a configuration writes it (``"16384 Hz"``).
    check : str
        What a drive's response at its collocated readback should be, in the site's words.
    fields : mapping of str to mapping of str to str
        Each field's words: the test point's word to the model's.
    rules : mapping of str to tuple of Rule
        ``drives``, ``readbacks``, ``shapes``, ``collocated``, ``damping``.
    source : str
        The table's file.
    """

    site: str
    ifo: str
    system: str
    rate: str
    check: str
    fields: Mapping[str, Mapping[str, str]]
    rules: Mapping[str, tuple[Rule, ...]]
    source: str

    def entries(self, kind: str, model: StateSpace) -> list[Entry]:
        """Every entry of `kind`'s rules whose model names `model` has, each site-side name
        once (the first rule that makes it)."""
        out: dict[str, Entry] = {}
        for rule in self.rules.get(kind, ()):
            for entry in self._expand(rule, model):
                key = entry.point or entry.names.get("input", "")
                out.setdefault(key, entry)
        return list(out.values())

    def guess(self, kind: str, point: str, model: StateSpace) -> Entry | None:
        """The entry of `kind` (``drives`` or ``readbacks``) a test point's suffix `point`
        has in `model` by the rules, or None."""
        return next((e for e in self.entries(kind, model) if e.point == point), None)

    def _expand(self, rule: Rule, model: StateSpace) -> Iterator[Entry]:
        """The rule filled with each choice of its fields' words, where the model has a
        candidate on every side."""
        names = list(rule.fields())
        for choice in itertools.product(*(self.fields[n].items() for n in names)):
            site = {n: w for n, (w, _) in zip(names, choice, strict=True)}
            ours = {n: m for n, (_, m) in zip(names, choice, strict=True)}
            found = {side: _first([c.format(**ours) for c in cands], model, side)
                     for side, cands in rule.sides.items()}
            if all(found.values()):
                yield Entry(rule.point.format(**site), found, rule, site)


def _first(candidates: Sequence[str], model: StateSpace, side: str) -> str | None:
    """The first candidate `model` has as an `side` (``input`` or ``output``), as a
    configuration names it: its last path component when that alone is unambiguous."""
    names = model.inputs if side == "input" else model.outputs
    for c in candidates:
        if c in names:
            return c
        if sum(1 for n in names if n.rsplit("/", 1)[-1] == c) == 1:
            return c
    return None


# ------------------------------------------------------------------------------ reading
def load_naming(path: str | Path) -> Naming:
    """The naming table at `path`.

    Raises
    ------
    ConfigError
        Naming the file, the key and the problem: an unknown key, a template whose field
        [fields] lacks, a candidate that is not text.
    """
    r = Reader(str(path), read_toml(Path(path)))
    r.only(["naming", *KINDS, "fields"])
    head = r.sub("naming")
    head.only(["site", "ifo", "system", "rate", "check"])
    fields = _fields(r.sub("fields"))
    rules = {kind: tuple(_rule(r, kind, i, fields) for i in range(len(_array(r, kind))))
             for kind in KINDS}
    return Naming(head.get("site", str), head.get("ifo", str), head.get("system", str),
                  head.get("rate", str, "16384 Hz"), head.get("check", str, ""), fields, rules,
                  str(path))


def default_naming(ifo: str) -> Naming | None:
    """The naming table twind ships for interferometer `ifo` (its ``[naming] ifo``), if any."""
    return next((n for n in shipped_namings() if n.ifo == ifo), None)


@functools.lru_cache(maxsize=1)
def shipped_namings() -> tuple[Naming, ...]:
    """Every naming table twind ships (read once)."""
    return tuple(load_naming(p) for p in sorted(SITES.glob(f"*/{NAMING_FILE}")))


def _fields(r: Reader) -> dict[str, dict[str, str]]:
    out = {}
    for name, words in r.table.items():
        if isinstance(words, list) and all(isinstance(w, str) for w in words):
            out[name] = {w: w for w in words}
        elif isinstance(words, dict) and all(isinstance(w, str) for w in words.values()):
            out[name] = dict(words)
        else:
            raise r.fail(name, f"expected a list of words or a table of word = model word, "
                         f"got {words!r}")
    return out


def _array(r: Reader, kind: str) -> list:
    value = r.table.get(kind, [])
    if not isinstance(value, list) or not all(isinstance(x, dict) for x in value):
        raise r.fail(kind, f"expected an array of tables ([[{kind}]]), got {value!r}")
    return value


def _rule(r: Reader, kind: str, i: int, fields: Mapping[str, Mapping[str, str]]) -> Rule:
    """The `i`-th rule of `kind`, its templates' fields checked against [fields]."""
    own = Reader(r.source, _array(r, kind)[i], f"{kind}[{i}].")
    key, sides = KINDS[kind]
    if kind == "damping":
        own.only(["module", "drive", "note", "gain", "on", "limit",
                  *(f"FM{k}" for k in range(1, 11))])
        own.get("drive", str)
    else:
        own.only([k for k in (key, *sides, "source") if k])
    rule = Rule(own.get(key, str) if key else "",
                {side: own.get(side, _candidates) for side in sides},
                {k: v for k, v in own.table.items() if k not in (key, *sides)})
    unknown = [f for f in rule.fields() if f not in fields]
    if unknown:
        raise own.fail(key or sides[0], f"uses {{{unknown[0]}}}, which [fields] does not "
                       f"define; it has {', '.join(fields)}")
    return rule


def _candidates(v: object) -> tuple[str, ...]:
    values = [v] if isinstance(v, str) else v
    if not (isinstance(values, list) and values and all(isinstance(x, str) for x in values)):
        msg = f"expected a model name or a list of them, got {v!r}"
        raise ValueError(msg)
    return tuple(values)


# ------------------------------------------------------------------------------ messages
def missing_line(naming: Naming | None, kind: str, point: str, model: StateSpace) -> str | None:
    """The line a configuration lacks for test point `point` (``drives`` or ``readbacks``),
    e.g. ``TM_LOCK_Y = "exc_TMY"``, guessed by `naming`'s rules; None without a guess."""
    entry = naming.guess(kind, point, model) if naming else None
    if entry is None:
        return None
    return f'{point} = "{entry.names["input" if kind == "drives" else "output"]}"'


def guessed_from(naming: Naming) -> str:
    """How a message says where a guess came from."""
    return f"guessed from {naming.site}'s naming; check it"


def existing_table(source: str, key: str, path: Path) -> Path:
    """`path` if it is a file; else the ConfigError naming `key` of `source`."""
    if not path.is_file():
        raise ConfigError(source, key, f"no naming table {path}")
    return path
