"""An optic whose plant is a state-space model another lab wrote, and the table that maps the
model's inputs and outputs to the site's test points.

The file (``twind/configs/kagra/SRM.toml`` is one)::

    [optic]
    name = "SRM"
    model = "statespace"

    [channels]            # the site's names: <ifo>:<system>-<OPTIC>_<suffix>
    ifo = "K1"
    system = "VIS"
    naming = "naming.toml" # optional: the site's naming rules (twind.config.naming), by
                           # default the table twind ships for the ifo (KAGRA's for K1)

    [statespace]
    file = "SRM_safe.mat" # beside this file: a .mat struct (a, b, c, d, names) or bare A..D
    source = "where the model comes from"
    rate = "16384 Hz"     # the front end's rate: what an engine integrates it at
    [statespace.shapes]   # a DOF: a collocated model input and output (labels each mode)
    "TM P" = ["f_TMP", "dispTMP"]

    [drives]              # an excitation test point (its suffix less _EXC): the input it drives
    TM_TEST_P = "exc_TMP"

    [readbacks]           # a channel's suffix: the model output it reads
    IM_DAMP_P_IN1 = "OSEM_IMP"

    [damping.IM_DAMP_P]   # a damping loop: IN1 is <module>_IN1, IN2 = IN1 + EXC, OUT = K IN2
    drive = "exc_IMP"     # the input OUT drives
    gain = -0.5           # its controller (optional: analysis needs none, an engine does)
    FM1 = ["vel", "zpk([0],[1;1],1)"]
    on = [1]

Every name is checked against the model when the file is read.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from twind.channels import Convention
from twind.config.naming import Naming, default_naming, existing_table, load_naming
from twind.config.reader import (
    ModuleConfig,
    Reader,
    fm_numbers,
    non_negative_quantity,
    positive_quantity,
    stage,
)
from twind.errors import ConfigError
from twind.loop.filtermodule import N_STAGES
from twind.model.statespace import ModalForm, StateSpace, StateSpaceError, modal_form, read_mat
from twind.simulation.statespace import StateSpaceEngine

SENSOR_NOISE = 1e-3
"""Each readback's white noise when the optic is simulated or served (per rtHz, in the
model's units: a thousandth of the excitations' unit DC response)."""


@dataclass(frozen=True)
class LoopSpec:
    """One damping loop of a state-space optic.

    Its filter module (its key in :attr:`StateSpaceOptic.loops`, e.g. ``IM_DAMP_L``) has the
    test points ``<module>_EXC`` ... ``_OUT``; its IN1 is the readback ``<module>_IN1``.

    Attributes
    ----------
    drive : str
        The model input its OUT drives.
    filters : ModuleConfig or None
        Its controller, if the file gives one.
    """

    drive: str
    filters: ModuleConfig | None = None


@dataclass(frozen=True, eq=False)
class StateSpaceOptic:
    """Everything twind knows of an optic whose plant is a state-space model.

    Attributes
    ----------
    name : str
    convention : Convention
        How its site names test points.
    model : StateSpace
    drives : mapping of str to str
        An excitation test point's suffix (less ``_EXC``) to the model input it drives.
    readbacks : mapping of str to str
        A channel's suffix to the model output it reads.
    loops : mapping of str to LoopSpec
        The damping loops, by module.
    shapes : mapping of str to (str, str)
        A DOF's label to a collocated model input and output (:func:`modal_form`).
    rate_hz : float
        The front end's sample rate.
    model_source : str
        Where the model comes from, as the file says.
    source : str
        The configuration file.
    naming : Naming or None
        The site's naming rules, which guess the line a configuration lacks for a point a
        file holds (:mod:`twind.config.naming`).
    """

    name: str
    convention: Convention
    model: StateSpace
    drives: Mapping[str, str]
    readbacks: Mapping[str, str]
    loops: Mapping[str, LoopSpec] = field(default_factory=dict)
    shapes: Mapping[str, tuple[str, str]] = field(default_factory=dict)
    rate_hz: float = 16384.0
    model_source: str = ""
    source: str = "<defaults>"
    naming: Naming | None = None

    kind = "statespace"

    def channel(self, suffix: str) -> str:
        """The full name of this optic's test point `suffix` (e.g. ``K1:VIS-SRM_IM_DAMP_L_IN1``)."""
        return self.convention.channel(self.name, suffix)

    def input_of(self, drive: str) -> str:
        """The model input that excitation point `drive` (a TEST point, or a damping loop's
        module whose OUT drives) drives."""
        if drive in self.drives:
            return self.drives[drive]
        if drive in self.loops:
            return self.loops[drive].drive
        msg = f"no drive {drive!r}; it has {', '.join([*self.drives, *self.loops])}"
        raise ConfigError(self.source, "drives", msg)

    def engine(self, rate_hz: float | None = None, max_hz: float | None = None,
               noise: Mapping[str, float] | None = None, seed: int = 0,
               closed: Sequence[str] | None = None) -> StateSpaceEngine:
        """The optic in a fixed-step engine
        (:class:`~twind.simulation.statespace.StateSpaceEngine`),
        at its front-end rate unless `rate_hz` is given; the other arguments are the
        engine's."""
        loops = {m: (spec.drive, spec.filters.build() if spec.filters else None)
                 for m, spec in self.loops.items()}
        return StateSpaceEngine(self.name, self.model, self.drives, self.readbacks, loops,
                                rate_hz or self.rate_hz, max_hz, noise, seed, closed)

    def modal(self, drives: tuple[str, ...], readbacks: tuple[str, ...]) -> ModalForm:
        """The model's modal form between `drives` (excitation points) and `readbacks`
        (channel suffixes), with its modes labelled by the shapes; made once per pair of
        lists."""
        return _modal(self, drives, readbacks)


@functools.lru_cache(maxsize=32)
def _modal(optic: StateSpaceOptic, drives: tuple[str, ...], readbacks: tuple[str, ...]
           ) -> ModalForm:
    return modal_form(optic.model, [optic.input_of(d) for d in drives],
                      [optic.readbacks[r] for r in readbacks], optic.shapes)


def load_statespace_optic(r: Reader, name: str) -> StateSpaceOptic:
    """The state-space optic of the file `r` walks (its ``[optic]`` already read).

    Parameters
    ----------
    r : Reader
        The whole file.
    name : str
        The optic's name.

    Returns
    -------
    StateSpaceOptic

    Raises
    ------
    ConfigError
        Naming the file, the key and the problem: a model that cannot be read, a name the
        model does not have, a loop without its readback.
    """
    r.only(["optic", "channels", "statespace", "drives", "readbacks", "damping"])
    channels = r.sub("channels")
    channels.only(["ifo", "system", "naming"])
    convention = Convention(channels.get("ifo", _name), channels.get("system", _name))
    naming = _naming(channels, convention.ifo)
    spec = r.sub("statespace")
    spec.only(["file", "variable", "source", "rate", "shapes"])
    model = _model(spec)
    rate = spec.get("rate", positive_quantity("frequency"), 16384.0)
    drives = _table(r.sub("drives"), model, "input")
    readbacks = _table(r.sub("readbacks"), model, "output")
    shapes = _shapes(spec.sub("shapes", required=False), model)
    loops = _loops(r.sub("damping", required=False), model, readbacks, rate)
    return StateSpaceOptic(name, convention, model, drives, readbacks, loops, shapes, rate,
                           spec.get("source", str, ""), r.source, naming)


def _name(v: object) -> str:
    if not (isinstance(v, str) and v.isalnum()):
        msg = f"expected letters and digits, e.g. \"K1\", got {v!r}"
        raise ValueError(msg)
    return v


def _naming(channels: Reader, ifo: str) -> Naming | None:
    """The naming table ``naming`` names (relative to the configuration file), else the one
    twind ships for `ifo`."""
    file = channels.get("naming", str, None)
    if file is None:
        return default_naming(ifo)
    return load_naming(existing_table(channels.source, channels.key("naming"),
                                      Path(channels.source).parent / file))


def _model(spec: Reader) -> StateSpace:
    """The model file named by ``file`` (relative to the configuration file)."""
    file = spec.get("file", str)
    try:
        return read_mat(Path(spec.source).parent / file, spec.get("variable", str, None))
    except StateSpaceError as err:
        raise spec.fail("file", str(err)) from None


def _table(r: Reader, model: StateSpace, kind: str) -> dict[str, str]:
    """A table of test points to model inputs (or outputs), each name checked."""
    out = {}
    for key, value in r.table.items():
        if not isinstance(value, str):
            raise r.fail(key, f"expected the name of a model {kind}, got {value!r}")
        try:
            (model.input_index if kind == "input" else model.output_index)(value)
        except StateSpaceError as err:
            raise r.fail(key, str(err)) from None
        out[key] = value
    if not out:
        raise r.fail("", f"names no test point; give at least one (suffix = \"model {kind}\")")
    return out


def _shapes(r: Reader, model: StateSpace) -> dict[str, tuple[str, str]]:
    """The DOFs that label modes: each a collocated ``[input, output]`` of the model."""
    out = {}
    for label, pair in r.table.items():
        if not (isinstance(pair, list) and len(pair) == 2
                and all(isinstance(x, str) for x in pair)):
            raise r.fail(label, f"expected [\"model input\", \"model output\"], got {pair!r}")
        try:
            model.input_index(pair[0])
            model.output_index(pair[1])
        except StateSpaceError as err:
            raise r.fail(label, str(err)) from None
        out[label] = (pair[0], pair[1])
    return out


def _loops(r: Reader, model: StateSpace, readbacks: Mapping[str, str], rate_hz: float
           ) -> dict[str, LoopSpec]:
    """The damping loops: each module's IN1 among the readbacks, its drive a model input,
    and its controller if given."""
    loops = {}
    fms = [f"FM{i}" for i in range(1, N_STAGES + 1)]
    for module in r.table:
        own = r.sub(module)
        own.only(["drive", "gain", "on", "limit", *fms])  # no ramp: its gain is not changed live
        drive = own.get("drive", str)
        try:
            model.input_index(drive)
        except StateSpaceError as err:
            raise own.fail("drive", str(err)) from None
        in1 = f"{module}_IN1"
        if in1 not in readbacks:
            raise r.fail(module, f"its IN1 ({in1}) is not among the readbacks; add "
                         f"{in1} = \"model output\" to [readbacks]")
        filters = None
        if "gain" in own.table:
            stages = tuple(own.get(fm, stage(rate_hz), None) for fm in fms)
            on = own.get("on", fm_numbers, ())
            for fm in on:
                if stages[fm - 1] is None:
                    raise own.fail("on", f"FM{fm} is switched on but holds no filter")
            filters = ModuleConfig(own.get("gain", _gain), stages, on,
                                   limit=own.get("limit", non_negative_quantity("counts"), 0.0))
        loops[module] = LoopSpec(drive, filters)
    return loops


def _gain(v: object) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        msg = f"expected a plain number (the model's units are its own), got {v!r}"
        raise ValueError(msg)
    return float(v)
