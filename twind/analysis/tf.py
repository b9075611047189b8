"""Transfer functions from the damping loop's test points: IN1/EXC, IN2/EXC, OUT/EXC, each
with its coherence and standard error, assembled into [response DOF x excited DOF] matrices,
and the open-loop plant recovered from them (seed eq. 14, MODEL.md's sign convention):

    P = (IN1/EXC) (IN2/EXC)^-1 K^-1 = (IN1/EXC) (OUT/EXC)^-1

Sources: diaggui "Fourier tools" XML files (one per excited DOF, read with dttxml) and MCAP
sessions of the twin (excitation segments from the recorded injection events; Welch estimates
with scipy.signal). The standard error of a Welch estimate is Bendat & Piersol's
``|H| sqrt((1 - g^2) / (2 n g^2))`` for ``n`` averages and coherence ``g^2``.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from twind import DOFS
from twind.errors import TwindError

POINTS = ("IN1", "IN2", "OUT")
_CHANNEL = re.compile(r"^(?P<ifo>\w+):SUS-(?P<optic>\w+?)_SUS(?P<dof>POS|PIT|YAW|SIDE)_(?P<point>\w+)$")


class TFError(TwindError):
    """A measurement cannot be turned into transfer functions."""


@dataclass
class TFSet:
    """Closed-loop transfer functions of one optic, one column per excited DOF.

    Arrays are indexed ``[frequency, response DOF, excited DOF]``.
    """

    optic: str
    frequency_hz: NDArray[np.float64]
    excited: list[str]
    responses: list[str]
    tf: dict[str, NDArray[np.complex128]]  # "IN1", "IN2", "OUT" per EXC
    coherence: dict[str, NDArray[np.float64]]
    averages: int

    def sigma(self, point: str) -> NDArray[np.float64]:
        """Standard error of each element of ``point``/EXC (Bendat & Piersol)."""
        g2 = np.clip(self.coherence[point], 1e-12, 1.0)
        return np.abs(self.tf[point]) * np.sqrt((1 - g2) / (2 * self.averages * g2))

    def plant(self) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
        """The open-loop plant over the excited DOFs and its standard error.

        ``P = (IN1/EXC)(OUT/EXC)^-1`` restricted to the excited DOFs' rows; the error is
        propagated to first order from the errors of both matrices, taken as independent.
        Both come from the same noise, so the sigma is conservative: the residuals of a
        twin recording against its model have about half the power it predicts
        (tests/test_tf.py); the identification issue calibrates it.
        """
        rows = [self.responses.index(d) for d in self.excited]
        m1 = self.tf["IN1"][:, rows, :]
        mo = self.tf["OUT"][:, rows, :]
        s1 = self.sigma("IN1")[:, rows, :]
        so = self.sigma("OUT")[:, rows, :]
        inv = np.linalg.inv(mo)
        P = m1 @ inv
        # dP = dM1 inv - P dMO inv: variances add element by element
        var = (s1**2) @ (np.abs(inv) ** 2) + (np.abs(P) ** 2) @ (so**2) @ (np.abs(inv) ** 2)
        return P, np.sqrt(var)

    def band(self, lo: float, hi: float) -> TFSet:
        """Only the frequencies in [lo, hi]."""
        keep = (self.frequency_hz >= lo) & (self.frequency_hz <= hi)
        return TFSet(self.optic, self.frequency_hz[keep], self.excited, self.responses,
                     {k: v[keep] for k, v in self.tf.items()},
                     {k: v[keep] for k, v in self.coherence.items()}, self.averages)

    def write(self, path: str | Path) -> Path:
        """HDF5 (``.h5``/``.hdf5``: one complex dataset per test point, coherence, errors,
        plant) or CSV (``.csv``: one row per frequency, columns named like
        ``IN1_POS_per_PIT_re``). An existing file is refused."""
        path = Path(path)
        if path.exists():
            msg = f"{path} exists; twind does not overwrite results"
            raise TFError(msg)
        P, Ps = self.plant()
        if path.suffix.lower() in (".h5", ".hdf5"):
            import h5py

            with h5py.File(path, "x") as f:
                f.attrs.update(optic=self.optic, excited=self.excited, responses=self.responses,
                               averages=self.averages)
                f["frequency_hz"] = self.frequency_hz
                for p in POINTS:
                    f[f"{p}_per_EXC"] = self.tf[p]
                    f[f"coherence_{p}"] = self.coherence[p]
                    f[f"sigma_{p}"] = self.sigma(p)
                f["plant"], f["plant_sigma"] = P, Ps
            return path
        if path.suffix.lower() == ".csv":
            cols, names = [self.frequency_hz], ["frequency_hz"]
            for p in POINTS:
                for i, r in enumerate(self.responses):
                    for j, e in enumerate(self.excited):
                        h = self.tf[p][:, i, j]
                        cols += [h.real, h.imag, self.coherence[p][:, i, j], self.sigma(p)[:, i, j]]
                        names += [f"{p}_{r}_per_{e}_{x}" for x in ("re", "im", "coh", "sigma")]
            for i, r in enumerate(self.excited):
                for j, e in enumerate(self.excited):
                    cols += [P[:, i, j].real, P[:, i, j].imag, Ps[:, i, j]]
                    names += [f"plant_{r}_per_{e}_{x}" for x in ("re", "im", "sigma")]
            np.savetxt(path, np.column_stack(cols), delimiter=",", header=",".join(names),
                       comments="")
            return path
        msg = f"{path}: write .h5, .hdf5 or .csv (or .png for a plot)"
        raise TFError(msg)

    def to_json(self) -> dict:
        """The ``twind tf --json`` object."""
        P, Ps = self.plant()

        def cplx(a: NDArray) -> dict:
            return {"re": a.real.tolist(), "im": a.imag.tolist()}

        return {"optic": self.optic, "frequency_hz": self.frequency_hz.tolist(),
                "excited": self.excited, "responses": self.responses,
                "IN1_per_EXC": cplx(self.tf["IN1"]), "IN2_per_EXC": cplx(self.tf["IN2"]),
                "OUT_per_EXC": cplx(self.tf["OUT"]),
                "coherence_IN1": self.coherence["IN1"].tolist(),
                "sigma_IN1": self.sigma("IN1").tolist(), "plant": cplx(P),
                "plant_sigma": Ps.tolist(), "averages": self.averages}


# ------------------------------------------------------------------------------ diaggui XML
def from_diaggui(paths: Sequence[str | Path]) -> TFSet:
    """Transfer functions from diaggui XML files, one per excited DOF (dttxml's ``xfer``)."""
    import dttxml

    columns, freq, optic, averages = {}, None, None, None
    for path in paths:
        try:
            acc = dttxml.DiagAccess(str(path))
        except Exception as err:  # noqa: BLE001 - dttxml raises many kinds on a bad file
            msg = f"{path}: not a readable diaggui XML file ({type(err).__name__}: {err})"
            raise TFError(msg) from None
        names = sorted(acc.channels()[0])
        exc = [n for n in names if n.endswith("_EXC") and _CHANNEL.match(n)]
        if len(exc) != 1:
            msg = f"{path}: expected one SUS ..._EXC channel (channel A), found {exc or 'none'}"
            raise TFError(msg)
        m = _CHANNEL.match(exc[0])
        optic = optic or m["optic"]
        if m["optic"] != optic:
            msg = f"{path}: excites {m['optic']}, the other files {optic}"
            raise TFError(msg)
        column = {}
        for dof in DOFS:
            for point in POINTS:
                name = f"{m['ifo']}:SUS-{optic}_SUS{dof}_{point}"
                if name not in names:
                    continue
                f, h, g2, n = xml_transfer(acc, name, exc[0])
                if freq is None:
                    freq, averages = f, n
                elif len(f) != len(freq) or np.max(np.abs(f - freq)) > 1e-9:
                    msg = f"{path}: its frequency bins differ from the other files'"
                    raise TFError(msg)
                column[(dof, point)] = (h, g2)
        columns[m["dof"]] = column
    return _assemble(optic, freq, columns, averages)


def xml_transfer(acc, numerator: str, denominator: str):  # noqa: ANN001, ANN201
    """``numerator/denominator`` of a diaggui measurement (a ``dttxml.DiagAccess`` or a
    path): frequencies, transfer function, coherence and number of averages."""
    import dttxml

    if not hasattr(acc, "xfer"):
        acc = dttxml.DiagAccess(str(acc))
    x = acc.xfer(numerator, denominator)
    return (np.asarray(x.FHz, dtype=float), np.asarray(x.xfer, dtype=complex),
            np.asarray(x.coh, dtype=float), int(x.averages))


def _assemble(optic: str, freq: NDArray, columns: dict, averages: int) -> TFSet:
    excited = [d for d in DOFS if d in columns]
    responses = [d for d in DOFS if all((d, p) in columns[e] for e in excited for p in POINTS)]
    if not excited or not set(excited) <= set(responses):
        msg = (f"need IN1, IN2 and OUT of every excited DOF in every measurement; excited "
               f"{excited}, complete responses {responses}")
        raise TFError(msg)
    shape = (len(freq), len(responses), len(excited))
    tf = {p: np.zeros(shape, dtype=complex) for p in POINTS}
    coh = {p: np.zeros(shape) for p in POINTS}
    for j, e in enumerate(excited):
        for i, r in enumerate(responses):
            for p in POINTS:
                tf[p][:, i, j], coh[p][:, i, j] = columns[e][(r, p)]
    return TFSet(optic, np.asarray(freq), excited, responses, tf, coh, averages)


# ------------------------------------------------------------------------------ MCAP sessions
def from_session(paths: Sequence[str | Path], bw: float = 0.01, overlap: float = 0.5,
                 optic: str | None = None) -> TFSet:
    """Welch transfer functions of the excitations recorded in MCAP sessions.

    Each excited DOF's segment runs from its injection's start to its end (the recorded
    ``start``/``end``/``stop`` events); Hann windows of ``1/bw`` seconds.
    """
    from twind.recording.reader import read_session

    session = read_session(list(paths))
    segments = _segments(session.events)
    if optic is not None:
        segments = {k: v for k, v in segments.items() if k[1] == optic}
    if not segments:
        msg = f"{', '.join(map(str, paths))}: no excitation segment found in the injection events"
        raise TFError(msg)
    optics = {k[1] for k in segments}
    if len(optics) > 1:
        msg = f"excitations on several optics {sorted(optics)}: choose one with --optic"
        raise TFError(msg)
    columns, freq, averages = {}, None, None
    for (ifo, name, dof), (start, end) in segments.items():
        exc_ch = session[f"{ifo}:SUS-{name}_SUS{dof}_EXC"]
        a, b = (int(round((t - exc_ch.t0) * exc_ch.rate)) for t in (start, end))
        x = exc_ch.samples[max(a, 0):b]
        nperseg = int(round(exc_ch.rate / bw))
        if x.size < nperseg:
            msg = f"the {dof} excitation lasts {x.size / exc_ch.rate:.1f} s, less than 1/bw = {1 / bw:g} s"
            raise TFError(msg)
        column = {}
        for r in DOFS:
            for p in POINTS:
                y = session[f"{ifo}:SUS-{name}_SUS{r}_{p}"].samples[max(a, 0):b]
                f, h, g2, n = welch_tf(x, y, exc_ch.rate, nperseg, overlap)
                column[(r, p)] = (h, g2)
        freq, averages = f, n
        columns[dof] = column
    return _assemble(next(iter(optics)), freq, columns, averages)


def welch_tf(x: NDArray, y: NDArray, rate: float, nperseg: int, overlap: float = 0.5
             ) -> tuple[NDArray, NDArray, NDArray, int]:
    """``H = CSD(x, y) / PSD(x)``, coherence, and the number of averages (scipy.signal)."""
    kw = {"fs": rate, "window": "hann", "nperseg": nperseg, "noverlap": int(nperseg * overlap)}
    f, pxy = signal.csd(x, y, **kw)
    _, pxx = signal.welch(x, **kw)
    _, g2 = signal.coherence(x, y, **kw)
    n = 1 + (len(x) - nperseg) // (nperseg - kw["noverlap"])
    return f, pxy / pxx, g2, n


def _segments(events: list[dict]) -> dict[tuple[str, str, str], tuple[float, float]]:
    starts, ends = {}, {}
    for ev in events:
        if ev.get("event") == "start":
            starts[ev["id"]] = (ev["channel"], ev["start_gps"])
            duration = (ev.get("request") or {}).get("duration")
            if isinstance(duration, (int, float)) and np.isfinite(duration):
                ends[ev["id"]] = ev["start_gps"] + duration
        elif ev.get("event") == "stop" and ev.get("id") in starts:
            ends[ev["id"]] = min(ends.get(ev["id"], np.inf), ev["gps"])
    out = {}
    for exc_id, (channel, start) in starts.items():
        m = _CHANNEL.match(channel)
        if m and exc_id in ends:
            out[(m["ifo"], m["optic"], m["dof"])] = (start, ends[exc_id])
    return out
