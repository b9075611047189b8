"""A measured set of transfer functions, :class:`TFSet`: the closed-loop responses of one
optic's test points (IN1/EXC, IN2/EXC, OUT/EXC) to each excited DOF, with their coherence and
standard error, and the open-loop plant recovered from them. Built once by a reader
(:mod:`twind.analysis.estimation.tf`), then only read: a changed set is a new one
(:func:`dataclasses.replace`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import h5py
import numpy as np
import scipy.io
from numpy.typing import NDArray
from scipy import stats

from twind.channels import dof_channel
from twind.errors import TwindError

__all__ = ["ESTIMATORS", "POINTS", "Kernel", "ReadOptions", "TFError", "TFSet",
           "coherence_floor", "register_reader"]

POINTS = ("IN1", "IN2", "OUT")
ESTIMATORS = ("welch", "lpm")
"""Welch's (diaggui's), or the local polynomial method's (:mod:`twind.analysis.estimation.lpm`)."""


class TFError(TwindError):
    """A measurement cannot be turned into transfer functions."""


@dataclass(frozen=True)
class Kernel:
    """What an estimate at frequency ``f`` sees of the true response of excited DOF ``e``:
    ``sum_r weights[f, r, e] G(f + offsets_hz[r])`` (the LPM's, which depends on the
    excitation's spectrum; :mod:`twind.analysis.estimation.lpm`)."""

    offsets_hz: NDArray[np.float64]  # (K,)
    weights: NDArray[np.complex128]  # (nf, K, n_excited)


def coherence_floor(averages: int, tests: int, at_least: float = 0.5,
                    false_alarm: float = 0.01) -> float:
    """The coherence a bin must reach to count as driven: `at_least`, and more than an
    undriven bin reaches in any of `tests` bins but with probability `false_alarm`.

    With ``n`` averages an undriven bin's estimate exceeds ``x`` with probability
    ``(1 - x)^(n - 1)`` (Carter, Knapp and Nuttall 1973): with 3 averages a quarter of the
    noise passes 0.5, and a recording's 800 000 bins reach it up to Nyquist.

    Parameters
    ----------
    averages : int
        Welch averages of the estimate (one: no bin can be told from noise).
    tests : int
        Bins (elements x frequencies) looked at together.
    at_least : float
        The floor whatever the averages.
    false_alarm : float
        Probability that noise alone passes in any of the `tests` bins.

    Returns
    -------
    float
        The coherence to reach (``inf`` with one average).

    Examples
    --------
    >>> round(coherence_floor(10, 36012), 3)
    0.813
    """
    if averages < 2:
        return math.inf  # one average's coherence is 1, whatever the signals
    return max(at_least, 1.0 - (false_alarm / max(tests, 1)) ** (1.0 / (averages - 1)))


@dataclass(frozen=True)
class ReadOptions:
    """How measurements are turned into transfer functions (the readers take what applies).

    Attributes
    ----------
    bw : float
        Resolution (Hz) of the estimates made from time series.
    overlap : float
        Fraction of a Welch segment shared with the next.
    optic : str, optional
        The optic, when several were excited.
    estimator : str
        ``"welch"`` or ``"lpm"`` (:data:`ESTIMATORS`).
    max_hz : float, optional
        Highest frequency wanted.
    mapping : mapping of str to str, optional
        A file's channel names to the twin's.
    exc_times : mapping of str to (float, float)
        Excited DOF to the GPS start and end of its excitation, where no event says them.
    """

    bw: float = 0.01
    overlap: float = 0.5
    optic: str | None = None
    estimator: str = "welch"
    max_hz: float | None = None
    mapping: Mapping[str, str] | None = None
    exc_times: Mapping[str, tuple[float, float]] = field(default_factory=dict)


Reader = Callable[[list[Path], ReadOptions], "TFSet"]
_READERS: dict[str, tuple[str, Callable[[list[Path]], bool], Reader]] = {}


def register_reader(name: str, what: str, identify: Callable[[list[Path]], bool],
                    reader: Reader) -> None:
    """Make :meth:`TFSet.read` take a format, as gwpy's ``io.registry`` does.

    Parameters
    ----------
    name : str
        The format's name (``"diaggui"``).
    what : str
        The files it takes, for an error message (``"diaggui .xml"``).
    identify : callable
        Whether a list of paths is of this format.
    reader : callable
        ``(paths, options) -> TFSet``.
    """
    _READERS[name] = (what, identify, reader)


def identify(paths: Sequence[str | Path]) -> str:
    """The registered format of measurement files (``"diaggui"``, ``"mcap"``, ``"frames"``).

    Raises
    ------
    TFError
        If the files are of no one registered format.
    """
    files = [Path(p) for p in paths]
    for name, (_, is_format, _) in _READERS.items():
        if files and is_format(files):
            return name
    kinds = sorted({p.suffix.lower() for p in files})
    msg = (f"inputs must be all {' or all '.join(w for w, _, _ in _READERS.values())}, "
           f"got {kinds}")
    raise TFError(msg)


@dataclass(frozen=True)
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
    window: str = "hann"  # of the spectral estimates: "hann" smooths H over ~1 bin; "lpm"
    exc_psd: dict[str, NDArray[np.float64]] | None = None  # per excited DOF, when known
    error: dict[str, NDArray[np.float64]] | None = None  # the estimator's own, when it has one
    kernel: Kernel | None = None  # when the estimate is not the TF at its frequency
    # correlation of the IN1/EXC errors of the responses, [f, response, response, excited]
    # (the LPM's; Welch's are taken as independent)
    in1_correlation: NDArray[np.complex128] | None = None
    found: tuple[str, ...] = ()  # the excitations found in the data (no injection events)
    ifo: str = "C1"  # the interferometer prefix of the channels measured
    # GPS start and end of each excited DOF's excitation; the end None where a file gives
    # only the start (diaggui)
    spans: dict[str, tuple[float, float | None]] = field(default_factory=dict)

    @classmethod
    def read(cls, paths: Sequence[str | Path], options: ReadOptions | None = None) -> TFSet:
        """The transfer functions of measurement files, whichever registered format they
        are in (:func:`register_reader`: diaggui XML, MCAP sessions, HDF5 or GWF files).

        Parameters
        ----------
        paths : sequence of path
            The files, all of one format.
        options : ReadOptions, optional
            How to estimate; the defaults otherwise.

        Returns
        -------
        TFSet

        Raises
        ------
        TFError
            A file that does not exist, or files of no one registered format.
        """
        files = [Path(p) for p in paths]
        missing = [str(p) for p in files if not p.exists()]
        if missing:
            msg = f"no such input: {', '.join(missing)}"
            raise TFError(msg)
        return _READERS[identify(files)][2](files, options or ReadOptions())

    def sigma(self, point: str) -> NDArray[np.float64]:
        """Standard error of the real and of the imaginary part of each element of
        ``point``/EXC: the estimator's own (the LPM's, from its residuals), else Bendat &
        Piersol's from the coherence."""
        if self.error is not None:
            return self.error[point]
        g2 = np.clip(self.coherence[point], 1e-12, 1.0)
        return np.abs(self.tf[point]) * np.sqrt((1 - g2) / (2 * self.averages * g2))

    def estimate(self) -> str:
        """How the TFs were estimated, for a title or a report: ``"Welch (hann), 19
        averages, 0.05 Hz bins"`` or ``"LPM, 0.0167 Hz bins"``."""
        f = self.frequency_hz
        df = f"{float(np.median(np.diff(f))):.3g} Hz bins" if f.size > 1 else "one bin"
        how = "LPM" if self.window == "lpm" else f"Welch ({self.window}), {self.averages} averages"
        return f"{how}, {df}"

    def description(self) -> dict[str, str]:
        """What a figure or report of these TFs shows: ``channels``, ``GPS`` span and
        ``estimate``."""
        points = "{IN1,IN2,OUT}/_EXC"
        starts = [a for a, _ in self.spans.values()]
        ends = [b for _, b in self.spans.values()]
        if not starts:
            gps = "not recorded"
        elif None in ends:
            gps = f"from {min(starts):.0f}"
        else:
            gps = f"{min(starts):.0f}-{max(ends):.0f}"
        return {"channels": f"{self.ifo}:SUS-{self.optic}_SUS<DOF>_{points}, "
                            f"<DOF> {', '.join(self.excited)}",
                "GPS": gps, "estimate": self.estimate()}

    def caption(self) -> str:
        """:meth:`description` in one line, for a figure."""
        return "; ".join(f"GPS {v}" if k == "GPS" else v for k, v in self.description().items())

    def plant(self) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
        """The open-loop plant over the excited DOFs and its standard error.

        ``P = (IN1/EXC)(OUT/EXC)^-1`` restricted to the excited DOFs' rows; the error is
        propagated to first order from the errors of both matrices, taken as independent.
        Both come from the same noise, so the sigma is conservative: the residuals of a
        twin recording against its model have about half the power it predicts
        (tests/test_tf.py).

        Returns
        -------
        P : ndarray, shape (nf, excited, excited)
            ``IN1/OUT`` (um/ct or urad/ct).
        sigma : ndarray, shape (nf, excited, excited)
            Standard error of its real and of its imaginary parts.
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

    def coherent(self, point: str = "IN1", at_least: float = 0.5) -> NDArray[np.bool_]:
        """The elements of ``point``/EXC driven by their excitation, bin by bin.

        Parameters
        ----------
        point : str
            ``IN1``, ``IN2`` or ``OUT``.
        at_least : float
            The coherence a bin must reach whatever the averages.

        Returns
        -------
        ndarray of bool, shape (nf, responses, excited)
            Where the coherence reaches :func:`coherence_floor` over every element.
        """
        g2 = self.coherence[point]
        return g2 >= coherence_floor(self.averages, g2.size, at_least)

    def coherent_band(self, at_least: float = 0.5) -> tuple[float, float] | None:
        """From the lowest to the highest frequency where some excited DOF's IN1 is driven by
        its own EXC (:meth:`coherent`, and for the LPM's estimates above their own errors at
        1 % over every bin): where the excitation reached the optic. None when no frequency
        is."""
        rows = [self.responses.index(d) for d in self.excited]
        own = self.coherent("IN1", at_least)[:, rows, np.arange(len(rows))]
        if self.error is not None:  # the LPM's: its coherence passes many undriven bins
            h = self.tf["IN1"][:, rows, np.arange(len(rows))]
            snr = np.abs(h) ** 2 / (2 * self.error["IN1"][:, rows, np.arange(len(rows))] ** 2)
            # |H / sigma|^2 / 2 of an undriven bin is F(2, 2n - 2): none of them passes
            own &= snr >= stats.f.isf(0.01 / snr.size, 2, 2 * max(self.averages - 1, 1))
        hit = np.flatnonzero(own.any(axis=1))
        f = self.frequency_hz
        return (float(f[hit[0]]), float(f[hit[-1]])) if hit.size else None

    def band(self, lo: float, hi: float) -> TFSet:
        """Only the frequencies in [lo, hi] (Hz).

        Parameters
        ----------
        lo, hi : float
            The band's edges (Hz), both kept.

        Returns
        -------
        TFSet

        Raises
        ------
        TFError
            If no measured frequency is in the band.
        """
        keep = (self.frequency_hz >= lo) & (self.frequency_hz <= hi)
        if not keep.any():
            msg = (f"no measured frequency in {lo:g}-{hi:g} Hz; the measurement covers "
                   f"{self.frequency_hz.min():g}-{self.frequency_hz.max():g} Hz")
            raise TFError(msg)
        return replace(
            self, frequency_hz=self.frequency_hz[keep],
            tf={k: v[keep] for k, v in self.tf.items()},
            coherence={k: v[keep] for k, v in self.coherence.items()},
            exc_psd={k: v[keep] for k, v in self.exc_psd.items()} if self.exc_psd else None,
            error={k: v[keep] for k, v in self.error.items()} if self.error else None,
            kernel=Kernel(self.kernel.offsets_hz, self.kernel.weights[keep])
            if self.kernel else None,
            in1_correlation=None if self.in1_correlation is None else self.in1_correlation[keep])

    def write(self, path: str | Path) -> Path:
        """Write the transfer functions, their coherence, errors and the plant.

        Parameters
        ----------
        path : path
            ``.h5``/``.hdf5`` (one complex dataset per test point), ``.csv`` (one row per
            frequency, columns named like ``IN1_POS_per_PIT_re``) or ``.mat`` (MATLAB:
            :meth:`write_mat`).

        Returns
        -------
        Path

        Raises
        ------
        TFError
            If the file exists (never overwritten) or its suffix is neither.
        """
        path = Path(path)
        if path.exists():
            msg = f"{path} exists; twind does not overwrite results"
            raise TFError(msg)
        P, Ps = self.plant()
        if path.suffix.lower() in (".h5", ".hdf5"):
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
        if path.suffix.lower() == ".mat":
            return self.write_mat(path)
        msg = f"{path}: write .h5, .hdf5, .csv or .mat (or .png for a plot)"
        raise TFError(msg)

    def write_mat(self, path: Path) -> Path:
        """A MATLAB file (``scipy.io.loadmat`` reads it too): 3-D arrays indexed
        ``[frequency, response, excited]``, ``IN1_per_EXC``, ``IN2_per_EXC``,
        ``OUT_per_EXC`` (complex), their ``coherence_*``, ``SNR_*`` (``g2 / (1 - g2)``,
        dttxml's and the seed's) and ``sigma_*``; ``plant`` and ``plant_sigma``
        (``[frequency, excited, excited]``); ``frequency_hz``; the channels as cell arrays
        (``EXC_channels`` by column, ``IN1_channels``... by row); ``optic``, ``excited``,
        ``responses``, ``averages``.
        """
        P, Ps = self.plant()

        def channels(dofs: list[str], point: str) -> NDArray:
            return np.array([dof_channel(self.ifo, self.optic, d, point) for d in dofs],
                            dtype=object)

        data = {"frequency_hz": self.frequency_hz, "optic": self.optic,
                "excited": np.array(self.excited, dtype=object),
                "responses": np.array(self.responses, dtype=object),
                "averages": self.averages, "EXC_channels": channels(self.excited, "EXC"),
                "plant": P, "plant_sigma": Ps}
        for p in POINTS:
            g2 = self.coherence[p]
            with np.errstate(divide="ignore"):
                data[f"SNR_{p}"] = g2 / (1 - g2)
            data.update({f"{p}_per_EXC": self.tf[p], f"coherence_{p}": g2,
                         f"sigma_{p}": self.sigma(p), f"{p}_channels": channels(
                             self.responses, p)})
        with path.open("xb") as f:
            scipy.io.savemat(f, data, do_compression=True)
        return path

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
