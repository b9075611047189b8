"""Configuration files: one TOML file per optic, and an interferometer file listing optics.

Every dimensional value is written ``"number unit"`` (see :mod:`twind.units`); unknown keys,
missing keys, wrong units, unreadable foton designs and an SOS's unstable loops are reported as
:class:`~twind.errors.ConfigError` naming the file, the key and the problem.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from twind import DOFS
from twind.channels import C1, Convention
from twind.config.reader import (
    ModuleConfig,
    Reader,
    boolean,
    fm_numbers,
    matrix,
    non_negative_quantity,
    positive,
    positive_int,
    positive_quantity,
    quantity,
    read_toml,
    stage,
)
from twind.config.statespace import StateSpaceOptic, load_statespace_optic
from twind.errors import ConfigError, TwindError
from twind.limits import ServiceLimits
from twind.loop.damping import DampingLoop
from twind.loop.filtermodule import N_STAGES, Stage
from twind.loop.foton_file import read_filter_file
from twind.model.analytical import analytical_mechanics
from twind.model.geometric import WireGeometry, geometric_model, wire_segments
from twind.model.matrices import CALIBRATION, input_matrix
from twind.model.mechanics import Mechanics
from twind.model.params import ALL_DOFS, SOSParams
from twind.model.plant import Plant
from twind.model.violin import Segment, Wire, sos_segments, with_violin_modes
from twind.simulation.discretize import closed_loop_matrices, closed_loop_modes, delay_samples
from twind.simulation.noise import NoiseSpec

CONFIG_DIR = Path(__file__).parent.parent / "configs"
DEFAULT_CONFIG = CONFIG_DIR / "c1.toml"
MEASURED_MODES = CONFIG_DIR / "measured" / "c1_free_swinging_2020.csv"
"""The 40m optics' measured free-swinging frequencies (source in the file)."""
NOMINAL_ETMX = CONFIG_DIR / "etmx_nominal.toml"
"""ETMX as LIGO-T000134 gives it, before any measurement: the optic of the golden responses."""

# config key -> (SOSParams field, dimension)
SUSPENSION_KEYS = {
    "mass": ("mass_kg", "mass"), "radius": ("radius_m", "length"),
    "thickness": ("thickness_m", "length"), "I_pitch": ("I_pitch_kgm2", "inertia"),
    "I_yaw": ("I_yaw_kgm2", "inertia"), "I_roll": ("I_roll_kgm2", "inertia"),
    "wire_length": ("wire_length_m", "length"), "b": ("b_m", "length"),
    "R1": ("R1_m", "length"), "R2": ("R2_m", "length"),
    "vertical_stiffness": ("vertical_stiffness_Npm", "stiffness"),
}
OSEM_KEYS = {"lever": ("osem_lever_m", "length"), "coil": ("coil_N_per_ct", "actuation"),
             "side_coil": ("side_coil_N_per_ct", "actuation")}
CDS_KEYS = {"rate": ("sample_rate_hz", "frequency"), "loop_delay": ("loop_delay_s", "time")}
WIRE_KEYS = {"diameter": ("diameter_m", "length"), "density": ("density_kgpm3", "density"),
             "youngs_modulus": ("youngs_modulus_Pa", "pressure")}
"""``[suspension.wire]`` keys with a unit; ``loss_angle`` and ``violin_modes`` are numbers."""
INPUT_MATRIX = "input_matrix"
"""``[cds]`` key of the input matrix as set in the front end: rows POS, PIT, YAW, SIDE (um, urad,
urad, um) per OSEM reading UL, UR, LL, LR, SIDE (um); default: the OSEM geometry's
(docs/model.md)."""
NOISE_KEYS = {"osem": ("osem_m", "length ASD"), "osem_corner": ("osem_corner_hz", "frequency"),
              "sp_x": ("sp_x_m", "length ASD"), "sp_y": ("sp_y_m", "length ASD"),
              "sp_phi": ("sp_phi_rad", "angle ASD"), "floor": ("floor_hz", "frequency")}
MODELS = ("analytical", "geometric", "statespace")
"""An SOS's rigid-body models, or a state-space model of any suspension
(:mod:`twind.config.statespace`)."""


@dataclass(frozen=True)
class OpticConfig:
    """Everything twind knows about one optic."""

    name: str
    sus: SOSParams
    damping: dict[str, ModuleConfig]
    noise: NoiseSpec = field(default_factory=NoiseSpec)
    model: str = "analytical"
    source: str = "<defaults>"
    input_matrix: tuple[tuple[float, ...], ...] | None = None  # [cds] input_matrix, if set

    kind = "sos"

    @property
    def rate_hz(self) -> float:
        """The model rate (Hz)."""
        return self.sus.sample_rate_hz

    def mechanics(self) -> Mechanics:
        """Dynamics of the configured model: the rigid body, with its wires' violin modes
        when ``[suspension.wire] violin_modes`` asks for them."""
        return with_violin_modes(*self._rigid(), self.sus.wire)

    def wire_segments(self) -> list[Segment]:
        """The wire segments of the configured model, with their own tensions and lengths
        (what the violin modes' frequencies follow, whether or not the model keeps them)."""
        return self._rigid()[1]

    def _rigid(self) -> tuple[Mechanics, list[Segment]]:
        """The rigid body's dynamics and its wire segments, of the one model configured."""
        if self.model == "geometric":
            model = geometric_model(WireGeometry.from_params(self.sus))
            return model.mechanics, wire_segments(model)
        mech = analytical_mechanics(self.sus)
        return mech, sos_segments(self.sus, mech.dofs)

    def plant(self, sus: SOSParams | None = None) -> Plant:
        """The optic's plant (with other suspension parameters `sus`, if given) behind its
        configured input matrix."""
        cfg = self if sus is None else replace(self, sus=sus)
        plant = Plant.from_params(cfg.sus, cfg.mechanics())
        if self.input_matrix is None:
            return plant
        return replace(plant, input_matrix=CALIBRATION * np.array(self.input_matrix))

    def cds_input_matrix(self) -> NDArray[np.float64]:
        """The input matrix as the front end holds it: DOF (um, urad) per OSEM um, (4, 5)."""
        if self.input_matrix is not None:
            return np.array(self.input_matrix)
        return input_matrix(self.sus.osem_lever_m) / CALIBRATION

    def loop(self) -> DampingLoop:
        """The optic's damping loop, with fresh filter modules."""
        return DampingLoop(self.name, self.plant(), {d: self.damping[d].build() for d in DOFS})

    @functools.cached_property
    def closed_loop_modes(self) -> list[tuple[float, float]]:
        """The damped suspension modes of its closed loop at the model rate, (Hz, Q) lowest
        first (:func:`~twind.simulation.discretize.closed_loop_modes`), found once: every
        fit's model asks."""
        return closed_loop_modes(self.loop(), self.sus.sample_rate_hz)


@dataclass(frozen=True)
class TwinConfig:
    """An interferometer's worth of optics, and what its service accepts."""

    ifo: str
    optics: dict[str, OpticConfig | StateSpaceOptic]
    source: str
    service: ServiceLimits = field(default_factory=ServiceLimits)
    convention: Convention = C1

    def select(self, names: Sequence[str] | str | None) -> list[OpticConfig | StateSpaceOptic]:
        """Optics by name (``"all"`` or None for every one), in the file's order."""
        if names is None or names == "all" or names == ["all"]:
            return list(self.optics.values())
        names = names.split(",") if isinstance(names, str) else list(names)
        unknown = [n for n in names if n not in self.optics]
        if unknown:
            msg = f"unknown optic(s) {', '.join(unknown)}; {self.source} has {', '.join(self.optics)}"
            raise ConfigError(self.source, "ifo.optics", msg)
        if len(set(names)) != len(names):
            raise ConfigError(self.source, "ifo.optics", f"an optic is named twice in {names}")
        chosen = [self.optics[n] for n in names]
        rates = {o.rate_hz for o in chosen}
        if len(rates) > 1:
            msg = f"optics run at different rates {sorted(rates)}; one engine runs one rate"
            raise ConfigError(self.source, "cds.rate", msg)
        return chosen


def _read_sus(r: Reader, name: str) -> SOSParams:
    sus, osem, cds = r.sub("suspension"), r.sub("osem"), r.sub("cds")
    values: dict[str, Any] = {"name": name}
    for reader, keys in ((sus, SUSPENSION_KEYS), (osem, OSEM_KEYS), (cds, CDS_KEYS)):
        reader.only([*keys, "Q", "wire"] if reader is sus else [*keys, INPUT_MATRIX]
                    if reader is cds else list(keys))
        for key, (attr, dim) in keys.items():
            values[attr] = reader.get(key, quantity(dim))
    q = sus.sub("Q")
    q.only(ALL_DOFS)
    values["Q"] = {d: q.get(d, positive) for d in ALL_DOFS}
    values["wire"] = _read_wire(sus.sub("wire", required=False))
    p = SOSParams(**values)
    for attr, problem in p.check():
        raise ConfigError(r.source, _config_key(attr), problem)
    return p


def _read_wire(wire: Reader) -> Wire:
    """``[suspension.wire]``: the wire's material and size, and how many violin modes of each
    segment the twin runs (none when the table or the key is missing)."""
    wire.only([*WIRE_KEYS, "loss_angle", "violin_modes"])
    default = Wire()
    values = {attr: wire.get(key, positive_quantity(dim), getattr(default, attr))
              for key, (attr, dim) in WIRE_KEYS.items()}
    values["loss_angle"] = wire.get("loss_angle", positive, default.loss_angle)
    values["modes"] = wire.get("violin_modes", _modes, 0)
    return Wire(**values)


def _modes(v: Any) -> int:
    if not (isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 20):
        msg = f"expected a whole number of modes 0..20, got {v!r}"
        raise ValueError(msg)
    return v


def _config_key(attr: str) -> str:
    for section, keys in (("suspension", SUSPENSION_KEYS), ("osem", OSEM_KEYS), ("cds", CDS_KEYS)):
        for key, (a, _) in keys.items():
            if a == attr:
                return f"{section}.{key}"
    return f"suspension.{attr}"


def _foton_file(damping: Reader):  # noqa: ANN202 - FilterFile or None
    """The foton file named by ``foton_file`` (relative to the config file), if any."""

    name = damping.get("foton_file", str, None)
    if name is None:
        return None
    try:
        return read_filter_file(Path(damping.source).parent / name)
    except TwindError as err:
        raise damping.fail("foton_file", str(err)) from None


def _file_stages(damping: Reader, ff, optic: str, dof: str,  # noqa: ANN001
                 rate_hz: float) -> tuple[Stage | None, ...]:
    """FM1..FM10 of the filter module ``<optic>_SUS<dof>`` of foton file `ff`."""
    path = ff.path
    module = f"{optic}_SUS{dof}"
    if module not in ff.modules:
        raise damping.fail("foton_file", f"{path} has no filter module {module}")
    if ff.rate_hz is not None and ff.rate_hz != rate_hz:
        raise damping.fail("foton_file", f"{path} is for {ff.rate_hz:g} Hz, the model runs at {rate_hz:g} Hz")
    stages: list[Stage | None] = [None] * N_STAGES
    for st in ff.modules[module]:
        stages[st.index] = Stage(st.name, st.design, st.sos, rate_hz)
    return tuple(stages)


def _read_damping(r: Reader, optic: str, rate_hz: float) -> dict[str, ModuleConfig]:
    damping = r.sub("damping")
    fms = [f"FM{i}" for i in range(1, N_STAGES + 1)]
    common = ["on", "ramp", "limit", *fms]
    damping.only([*common, "foton_file", *DOFS])
    ff = _foton_file(damping)
    modules = {}
    for dof in DOFS:
        own = damping.sub(dof)
        own.only(["gain", *common])

        def pick(key: str, convert: Callable[[Any], Any], default: Any = ..., own=own) -> Any:
            return own.get(key, convert, damping.get(key, convert, default))

        stages = tuple(pick(fm, stage(rate_hz), None) for fm in fms)
        if ff is not None:
            if any(stages):
                raise damping.fail("foton_file", "give the stages either as FMn designs or "
                                   "in a foton file, not both")
            stages = _file_stages(damping, ff, optic, dof, rate_hz)
        on = pick("on", fm_numbers, ())
        for fm in on:
            if stages[fm - 1] is None:
                where = own if "on" in own.table else damping
                raise where.fail("on", f"FM{fm} is switched on but holds no filter")
        modules[dof] = ModuleConfig(
            gain=own.get("gain", quantity("velocity gain")), stages=stages, on=on,
            ramp_s=pick("ramp", non_negative_quantity("time"), 0.0),
            limit=pick("limit", non_negative_quantity("counts"), 0.0))
    return modules


def _read_noise(r: Reader) -> NoiseSpec:
    noise = r.sub("noise", required=False)
    noise.only([*NOISE_KEYS, "enabled"])
    values = {attr: noise.get(key, positive_quantity(dim), getattr(NoiseSpec(), attr))
              for key, (attr, dim) in NOISE_KEYS.items()}
    values["enabled"] = noise.get("enabled", boolean, True)
    return NoiseSpec(**values)


def _check_model(v: Any) -> str:
    if v not in MODELS:
        msg = f"expected one of {', '.join(MODELS)}, got {v!r}"
        raise ValueError(msg)
    return v


def load_optic(path: str | Path) -> OpticConfig | StateSpaceOptic:
    """Read one optic's TOML file.

    Parameters
    ----------
    path : str or Path
        The file.

    Returns
    -------
    OpticConfig or StateSpaceOptic
        An SOS with its physical parameters, or a plant given as a state-space model
        (``model = "statespace"``, :mod:`twind.config.statespace`).

    Raises
    ------
    ConfigError
        Naming the file, the key and the problem.
    """
    source = str(path)
    r = Reader(source, read_toml(path))
    optic = r.sub("optic")
    optic.only(["name", "model"])
    name, model = optic.get("name", str), optic.get("model", _check_model, "analytical")
    if model == "statespace":
        return load_statespace_optic(r, name)
    r.only(["optic", "suspension", "osem", "cds", "damping", "noise"])
    sus = _read_sus(r, name)
    cfg = OpticConfig(name=name, sus=sus, damping=_read_damping(r, name, sus.sample_rate_hz),
                      noise=_read_noise(r), model=model, source=source,
                      input_matrix=r.sub("cds").get(INPUT_MATRIX, matrix(4, 5), None))
    check_stable(cfg)
    return cfg


def load_config(path: str | Path | None = None, optics: Sequence[str] | str | None = None) -> TwinConfig:
    """Read an interferometer file (``[ifo]`` with ``optics``) or a single optic's file.

    Parameters
    ----------
    path : str or Path, optional
        Defaults to the 40m file shipped with twind (:data:`DEFAULT_CONFIG`).
    optics : sequence of str or str, optional
        Read only these optics (comma-separated names, or ``"all"``, the default).

    Returns
    -------
    TwinConfig
    """
    path = Path(path) if path is not None else DEFAULT_CONFIG
    data = read_toml(path)
    if "ifo" not in data:
        optic = load_optic(path)
        convention = getattr(optic, "convention", C1)
        return TwinConfig(convention.ifo, {optic.name: optic}, str(path), convention=convention)
    r = Reader(str(path), data)
    r.only(["ifo", "service", "channels"])
    ifo = r.sub("ifo")
    ifo.only(["name", "optics"])
    files = optic_files(path)
    wanted = list(files) if optics in (None, "all", ["all"]) else (
        optics.split(",") if isinstance(optics, str) else list(optics))
    unknown = [n for n in wanted if n not in files]
    if unknown:
        raise ifo.fail("optics", f"unknown optic(s) {', '.join(unknown)}; the file has "
                       f"{', '.join(files)}")
    loaded = {name: load_optic(files[name]) for name in wanted}
    channels = r.sub("channels", False)
    channels.only(["system"])
    convention = Convention(ifo.get("name", str), channels.get("system", str, C1.system))
    for optic in loaded.values():
        own = getattr(optic, "convention", convention)
        if own != convention:
            raise channels.fail("system", f"{optic.name} names its channels {own.ifo}:"
                                f"{own.system}-..., this file {convention.ifo}:"
                                f"{convention.system}-...; make them agree")
    return TwinConfig(convention.ifo, loaded, str(path), _read_service(r.sub("service", False)),
                      convention)


def optic_files(path: str | Path | None = None) -> dict[str, Path]:
    """Each optic of an interferometer file and the file that holds it (in ``optics/`` or
    beside it), in the file's order, none of them read; a single optic's file holds one."""
    path = Path(path) if path is not None else DEFAULT_CONFIG
    data = read_toml(path)
    r = Reader(str(path), data)
    if "ifo" not in data:
        return {r.sub("optic").get("name", str): path}
    ifo = r.sub("ifo")
    out = {}
    for name in ifo.get("optics", lambda v: [str(x) for x in v]):
        file = path.parent / "optics" / f"{name}.toml"
        file = file if file.exists() else path.parent / f"{name}.toml"
        if not file.exists():
            raise ifo.fail("optics", f"no file {file} for optic {name} (in optics/ or beside it)")
        out[name] = file
    return out


def optic_kinds(path: str | Path | None = None) -> dict[str, str]:
    """Each optic's kind, ``"sos"`` or ``"statespace"``, from its ``[optic]`` table alone."""
    kinds = {}
    for name, file in optic_files(path).items():
        model = Reader(str(file), read_toml(file)).sub("optic").get("model", str, "analytical")
        kinds[name] = "statespace" if model == "statespace" else "sos"
    return kinds


def default_optic(path: str | Path | None = None) -> str:
    """The optic a command takes when none is named: the file's only one, else the 40m's
    ETMX; a ConfigError naming the choices when the file has several and no ETMX."""
    names = list(optic_files(path))
    if len(names) == 1 or "ETMX" in names:
        return names[0] if len(names) == 1 else "ETMX"
    source = str(path or DEFAULT_CONFIG)
    raise ConfigError(source, "ifo.optics", f"several optics ({', '.join(names)}): name one "
                      "with --optic (or --optics)")


def _read_service(r: Reader) -> ServiceLimits:
    """The ``[service]`` table: each key a positive number (counts whole)."""
    defaults = ServiceLimits()
    names = [f.name for f in fields(ServiceLimits)]
    r.only(names)
    return ServiceLimits(**{n: r.get(n, positive_int if isinstance(getattr(defaults, n), int)
                                     else positive, getattr(defaults, n)) for n in names})


def check_stable(cfg: OpticConfig) -> None:
    """Raise ConfigError when the optic's closed damping loop has a growing mode.

    The check uses the engine's own discrete closed loop, so what passes here runs.
    """

    try:
        delay_samples(cfg.sus.loop_delay_s, cfg.sus.sample_rate_hz)
    except ValueError as err:
        raise ConfigError(cfg.source, "cds.loop_delay", str(err)) from None
    poles = np.linalg.eigvals(closed_loop_matrices(cfg.loop(), cfg.sus.sample_rate_hz)[0])
    worst = poles[np.argmax(np.abs(poles))]
    if abs(worst) < 1.0:
        return
    f = abs(np.angle(worst)) * cfg.sus.sample_rate_hz / (2 * np.pi)
    msg = (f"the closed damping loop is unstable: a mode at {f:.3g} Hz grows by a factor "
           f"{abs(worst):.6f} per cycle; check the gains, signs and filters")
    raise ConfigError(cfg.source, f"damping.{_culprit(cfg)}", msg)


def _culprit(cfg: OpticConfig) -> str:
    """The DOF whose loop alone (other gains zero) is unstable, for the error message."""

    for dof in DOFS:
        loop = cfg.loop()
        for other in DOFS:
            if other != dof:
                loop.modules[other].gain = 0.0
        A = closed_loop_matrices(loop, cfg.sus.sample_rate_hz)[0]
        if np.abs(np.linalg.eigvals(A)).max() >= 1.0:
            return f"{dof}.gain"
    return "gain"
