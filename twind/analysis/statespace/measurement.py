"""A state-space optic's measured plant: each readback per drive, from diaggui files named in
the site's convention.

A file excites one test point (channel A, ``..._EXC``) and reads others (channels B):

* **open loop**: the excitation is a drive's test point (KAGRA's ``IM_TEST_P_EXC``), damping
  off: ``readback / EXC`` is the plant seen through the calibrations;
* **closed loop**: the excitation is a damping loop's ``EXC`` and the file holds the loop's
  ``IN1``, ``IN2`` and ``OUT``: the plant is ``(readback / EXC) / (OUT / EXC)``, the response
  per unit of the drive the loop's OUT is (the seed's equation 14, column by column), and the
  controller ``OUT / IN2`` (``IN2 = IN1 + EXC``).

Errors are Bendat and Piersol's from the coherence (:func:`error`); a closed loop's plant
propagates those of both ratios as independent (they share the noise, so the sigma is
conservative).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from twind.analysis.estimation.diaggui import Transfer, read_transfers
from twind.analysis.estimation.tfset import TFError, coherence_floor
from twind.analysis.identification.data import MIN_COHERENCE, SURE_COHERENCE, smoothed
from twind.config.naming import UnmappedReadbackWarning, guessed_from, missing_line
from twind.config.statespace import StateSpaceOptic


@dataclass(frozen=True)
class LoopTF:
    """A damping loop's own test points, over its EXC, in a closed-loop measurement.

    Attributes
    ----------
    module : str
        E.g. ``IM_DAMP_L``.
    tf : dict of str to ndarray
        ``IN1``, ``IN2``, ``OUT`` over EXC (those recorded).
    coherence : dict of str to ndarray
    """

    module: str
    tf: Mapping[str, NDArray[np.complex128]]
    coherence: Mapping[str, NDArray[np.float64]]
    averages: int

    def controller(self) -> tuple[NDArray[np.complex128], NDArray[np.float64]] | None:
        """``OUT / IN2`` and its standard error (None without both)."""
        if not {"OUT", "IN2"} <= set(self.tf):
            return None
        return _ratio(self.tf["OUT"], self.coherence["OUT"], self.tf["IN2"],
                      self.coherence["IN2"], self.averages)


@dataclass(frozen=True)
class PlantSet:
    """Measured plant of a state-space optic: readbacks (rows) per drive (columns).

    Arrays are indexed ``[frequency, readback, drive]``; an element a file did not read is
    NaN with zero coherence.

    Attributes
    ----------
    optic : str
    frequency_hz : ndarray
    drives : tuple of str
        The excitation points: a TEST point's suffix (open loop) or a damping loop's module
        (closed loop: the column is per unit of its OUT).
    readbacks : tuple of str
        Channel suffixes, as the configuration names them.
    H, sigma, coherence : ndarray
        The plant, the standard error of its real and imaginary parts, and its coherence
        (a closed loop's: the lower of the readback's and OUT's).
    averages : int
        The fewest of any file.
    channels : dict of str to str
        Each drive's and readback's full channel name.
    loops : dict of str to LoopTF
        The closed-loop columns' own test points.
    sources : tuple of str
        The files read.
    window : str
        ``"hann"`` (FFT measurements: each bin averages over the window's kernel) or
        ``"none"`` (swept sines: each point at its own frequency).
    gps : float or None
        The first measurement's start (GPS seconds), when the files have it.
    """

    optic: str
    frequency_hz: NDArray[np.float64]
    drives: tuple[str, ...]
    readbacks: tuple[str, ...]
    H: NDArray[np.complex128]
    sigma: NDArray[np.float64]
    coherence: NDArray[np.float64]
    averages: int
    channels: Mapping[str, str] = field(default_factory=dict)
    loops: Mapping[str, LoopTF] = field(default_factory=dict)
    sources: tuple[str, ...] = ()
    window: str = "hann"
    gps: float | None = None

    @property
    def resolution_hz(self) -> float:
        """The Hann bins' width (Hz); 0 for a swept sine's points, each its own frequency."""
        f = self.frequency_hz
        return float(np.median(np.diff(f))) if f.size > 1 and self.window == "hann" else 0.0

    def coherent(self, min_coherence: float = MIN_COHERENCE) -> NDArray[np.bool_]:
        """The bins to trust: their coherence averaged over neighbours reaches
        `min_coherence` (as an SOS's fit chooses them,
        :meth:`~twind.analysis.identification.data.FitData.from_tfset`), or their own reaches
        what noise alone does not; finite, above 0 Hz.

        Returns
        -------
        ndarray of bool, shape (nf, readbacks, drives)
        """
        g2 = np.nan_to_num(self.coherence)
        # a bin alone must reach what noise reaches in none of the file's bins but 1 % of
        # the time (with 5 averages and 10^5 bins, 0.98): diaggui's errors from a fluke's
        # coherence make it a huge residual
        alone = max(coherence_floor(self.averages, g2.size, SURE_COHERENCE), min_coherence)
        chosen = (smoothed(g2) >= min_coherence) | (g2 >= alone)
        return chosen & np.isfinite(self.H) & (self.sigma > 0) & \
            (self.frequency_hz > 0)[:, None, None]

    def band(self, lo: float, hi: float) -> PlantSet:
        """Only the frequencies in [lo, hi] (Hz); a TFError if none is."""
        keep = (self.frequency_hz >= lo) & (self.frequency_hz <= hi)
        if not keep.any():
            msg = (f"no measured frequency in {lo:g}-{hi:g} Hz; the measurement covers "
                   f"{self.frequency_hz.min():g}-{self.frequency_hz.max():g} Hz")
            raise TFError(msg)
        loops = {k: LoopTF(v.module, {p: x[keep] for p, x in v.tf.items()},
                           {p: x[keep] for p, x in v.coherence.items()}, v.averages)
                 for k, v in self.loops.items()}
        return PlantSet(self.optic, self.frequency_hz[keep], self.drives, self.readbacks,
                        self.H[keep], self.sigma[keep], self.coherence[keep], self.averages,
                        self.channels, loops, self.sources, self.window, self.gps)

    def to_json(self) -> dict:
        """The ``twind tf --json`` object: the plant, its errors, coherence, the bins
        trusted and their runs, and each closed loop's own test points and controller."""
        def cplx(a: NDArray) -> dict:
            return {"re": a.real.tolist(), "im": a.imag.tolist()}

        loops = {}
        for module, loop in self.loops.items():
            entry = {f"{p}_per_EXC": cplx(h) for p, h in loop.tf.items()}
            k = loop.controller()
            if k is not None:
                entry["controller_OUT_per_IN2"] = cplx(k[0])
                entry["controller_sigma"] = k[1].tolist()
            loops[module] = entry
        return {"optic": self.optic, "frequency_hz": self.frequency_hz.tolist(),
                "drives": list(self.drives), "readbacks": list(self.readbacks),
                "channels": dict(self.channels), "averages": self.averages,
                "plant": cplx(self.H), "sigma": self.sigma.tolist(),
                "coherence": self.coherence.tolist(), "coherent": self.coherent().tolist(),
                "coherent_bands": self.coherent_bands(), "sources": list(self.sources),
                "loops": loops}

    def coherent_bands(self, min_coherence: float = MIN_COHERENCE
                       ) -> dict[str, list[tuple[float, float]]]:
        """Each element's runs of coherent bins, as (lowest, highest) frequency (Hz)."""
        mask = self.coherent(min_coherence)
        f = self.frequency_hz
        out = {}
        for i, r in enumerate(self.readbacks):
            for j, d in enumerate(self.drives):
                idx = np.flatnonzero(mask[:, i, j])
                runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1) if idx.size else []
                out[f"{r}/{d}"] = [(float(f[x[0]]), float(f[x[-1]])) for x in runs if x.size]
        return out


def read_plant(paths: Sequence[str | Path], optic: StateSpaceOptic) -> PlantSet:
    """The plant of `optic` from diaggui files, one per excitation.

    Parameters
    ----------
    paths : sequence of path
        diaggui FFT (or swept sine) measurements: in each, one of the optic's excitation
        points as channel A and its readbacks (and a damping loop's IN1, IN2, OUT) as B.
    optic : StateSpaceOptic
        Its configuration: the convention and the tables name the channels.

    Returns
    -------
    PlantSet

    Raises
    ------
    TFError
        If a file has no excitation of the optic, reads none of its readbacks, a closed-loop
        file lacks the loop's OUT, or the files' frequencies differ.
    """
    columns: dict[str, dict[str, tuple]] = {}
    loops: dict[str, LoopTF] = {}
    channels: dict[str, str] = {}
    freq, averages, kinds, starts = None, [], set(), []
    for path in paths:
        transfers = read_transfers(path)
        starts += [t.gps for t in transfers if t.gps]
        drive, by_suffix = _by_suffix(path, transfers, optic)
        f = transfers[0].frequency_hz
        averages += [t.averages for t in transfers]
        kinds |= {t.kind for t in transfers}
        if freq is None:
            freq = f
        elif f.size != freq.size or np.max(np.abs(f - freq)) > 1e-9:
            msg = f"{path}: its frequency bins differ from the other files'"
            raise TFError(msg)
        if drive in columns:
            msg = f"{path}: {optic.channel(drive + '_EXC')} is excited in two files"
            raise TFError(msg)
        columns[drive], loop = _column(path, drive, by_suffix, optic)
        if loop is not None:
            loops[drive] = loop
        channels[drive] = optic.channel(f"{drive}_EXC")
    drives = tuple(columns)
    readbacks = tuple(r for r in optic.readbacks if any(r in c for c in columns.values()))
    shape = (freq.size, len(readbacks), len(drives))
    H = np.full(shape, np.nan, dtype=complex)
    sigma = np.zeros(shape)
    coh = np.zeros(shape)
    for j, d in enumerate(drives):
        for i, r in enumerate(readbacks):
            if r in columns[d]:
                H[:, i, j], sigma[:, i, j], coh[:, i, j] = columns[d][r]
    channels.update({r: optic.channel(r) for r in readbacks})
    return PlantSet(optic.name, np.asarray(freq), drives, readbacks, H, sigma, coh,
                    int(min(averages)), channels, loops, tuple(str(p) for p in paths),
                    "hann" if kinds == {"FFT"} else "none", min(starts, default=None))


def _by_suffix(path: str | Path, transfers: list[Transfer], optic: StateSpaceOptic
               ) -> tuple[str, dict[str, Transfer]]:
    """The excitation point of one file and its transfer functions by channel suffix."""
    excited = {optic.convention.parse(t.denominator) for t in transfers}
    ours = sorted({p[1][:-4] for p in excited if p and p[0] == optic.name
                   and p[1].endswith("_EXC")})
    if len(ours) != 1:
        found = sorted({t.denominator for t in transfers})
        example = optic.channel(f"{next(iter(optic.drives))}_EXC")
        msg = (f"{path}: expected one excitation of {optic.name} named like {example} "
               f"(channel A); the file's are {', '.join(found[:4])}")
        raise TFError(msg)
    drive = ours[0]
    if drive not in optic.drives and drive not in optic.loops:
        raise TFError(_not_a_drive(path, drive, optic))
    by = {}
    for t in transfers:
        a, b = optic.convention.parse(t.denominator), optic.convention.parse(t.numerator)
        if a == (optic.name, f"{drive}_EXC") and b and b[0] == optic.name:
            by[b[1]] = t
    _note_unmapped(path, by, optic)
    return drive, by


def _not_a_drive(path: str | Path, drive: str, optic: StateSpaceOptic) -> str:
    """The refusal of a file exciting a point the configuration lacks, with the line to add
    (the model input guessed by the site's naming where it can)."""
    head = (f"{path}: {optic.channel(drive + '_EXC')} is not a drive of "
            f"{Path(optic.source).name}: add ")
    line = missing_line(optic.naming, "drives", drive, optic.model)
    if line:
        return f"{head}{line} to its [drives] (the model input {guessed_from(optic.naming)})"
    return (f'{head}{drive} = "MODEL INPUT" to its [drives], naming the model input it '
            f"drives; its drives are {', '.join([*optic.drives, *optic.loops])}")


def _note_unmapped(path: str | Path, by: Mapping[str, Transfer], optic: StateSpaceOptic
                   ) -> None:
    """A note (:class:`~twind.config.naming.UnmappedReadbackWarning`) for each channel of
    the file the configuration does not read but the site's naming maps to a model output,
    with the line that would read it."""
    for suffix in by:
        line = None if suffix in optic.readbacks else missing_line(
            optic.naming, "readbacks", suffix, optic.model)
        if line:
            warnings.warn(f"{path}: {optic.channel(suffix)} is not a readback of "
                          f"{Path(optic.source).name}, left out: add {line} to its "
                          f"[readbacks] (the model output {guessed_from(optic.naming)})",
                          UnmappedReadbackWarning, stacklevel=4)


def _column(path: str | Path, drive: str, by: Mapping[str, Transfer], optic: StateSpaceOptic
            ) -> tuple[dict[str, tuple], LoopTF | None]:
    """One file's column: each readback's (plant, sigma, coherence), and the loop's own
    test points when the drive is a damping loop."""
    reads = [r for r in optic.readbacks if r in by]
    if not reads:
        msg = (f"{path}: reads none of {optic.name}'s readbacks "
               f"({', '.join(optic.channel(r) for r in list(optic.readbacks)[:3])} ...)")
        raise TFError(msg)
    if drive not in optic.loops:
        return {r: (by[r].tf, error(by[r].tf, by[r].coherence, by[r].averages),
                    by[r].coherence) for r in reads}, None
    points = {p: by[f"{drive}_{p}"] for p in ("IN1", "IN2", "OUT") if f"{drive}_{p}" in by}
    loop = LoopTF(drive, {p: t.tf for p, t in points.items()},
                  {p: t.coherence for p, t in points.items()}, by[reads[0]].averages)
    if "OUT" not in points:
        msg = (f"{path}: excites the damping loop {drive} but holds no "
               f"{optic.channel(drive + '_OUT')}: the plant is readback/OUT (record OUT, or "
               "excite the TEST point with damping off)")
        raise TFError(msg)
    out = points["OUT"]
    column = {}
    for r in reads:
        h, s = _ratio(by[r].tf, by[r].coherence, out.tf, out.coherence, by[r].averages)
        column[r] = (h, s, np.minimum(by[r].coherence, out.coherence))
    return column, loop


def error(h: NDArray[np.complex128], coherence: NDArray[np.float64], averages: int
          ) -> NDArray[np.float64]:
    """Bendat and Piersol's standard error of a Welch estimate, ``|H| sqrt((1 - g2) /
    (2 n g2))``, from the bin's own coherence or from its neighbours' mean, whichever gives
    the larger: with few averages a bin's coherence scatters up as often as down, and
    neighbours share the scatter, so where it happened high the bin's own error is
    understated several times and a cluster of them looks like a narrow mode; the
    neighbours' mean alone would understate it where the coherence truly dips (a notch).
    """
    return np.abs(h) * np.sqrt(_relative2(coherence, averages))


def _relative2(coherence: NDArray[np.float64], averages: int) -> NDArray[np.float64]:
    """The squared relative error (:func:`error`)."""
    g2 = np.clip(np.minimum(np.nan_to_num(coherence), smoothed(np.nan_to_num(coherence))),
                 1e-12, 1.0)
    return (1 - g2) / (2 * averages * g2)


def _ratio(num: NDArray, g_num: NDArray, den: NDArray, g_den: NDArray, averages: int
           ) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
    """``num / den`` of two estimates over one excitation, and its standard error, their
    relative errors (:func:`error`) added in quadrature."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = num / den
    rel2 = _relative2(g_num, averages) + _relative2(g_den, averages)
    return ratio, np.abs(ratio) * np.sqrt(rel2)
