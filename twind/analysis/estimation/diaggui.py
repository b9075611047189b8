"""diaggui measurements (LIGO_LW "Diagnostics Test" XML): read any, write FFT ones.

:func:`read_transfers` reads every transfer function of a file diaggui saved, Fourier tools
(FFT) or swept sine, whatever its channels (another observatory, subsystem or test point), each
with its coherence and standard errors. The writer makes FFT measurements as diaggui saves
them: one file per excited DOF, channel A the ``_EXC``, channels B the test points; a
PowerSpectrum (ASD, float) per channel, one CrossCorrelation (complex, B against A) and one
Coherence block over the B channels, indexed in the "Index" section. dttxml reads them back
(``xfer(B, A) = CSD / ASD_A^2``); twind writes them so that measurements made on the twin can
be handed around, and diagnosed, exactly like measurements made on an optic.
"""

from __future__ import annotations

import base64
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from xml.sax.saxutils import escape

import dttxml
import numpy as np
from numpy.typing import NDArray

from twind.analysis.estimation.tfset import POINTS, TFError, TFSet

_DTD = """<?xml version="1.0"?>
<!DOCTYPE LIGO_LW [
<!ELEMENT LIGO_LW ((LIGO_LW|Comment|Param|Time|Table|Array|Stream)*)>
<!ATTLIST LIGO_LW Name CDATA #IMPLIED Type CDATA #IMPLIED>
<!ELEMENT Comment (#PCDATA)>
<!ELEMENT Param (#PCDATA)>
<!ATTLIST Param Name CDATA #IMPLIED Type CDATA #IMPLIED Dim CDATA #IMPLIED
                Unit CDATA #IMPLIED>
<!ELEMENT Table (Comment?,Column*,Stream?)>
<!ATTLIST Table Name CDATA #IMPLIED Type CDATA #IMPLIED>
<!ELEMENT Column EMPTY>
<!ATTLIST Column Name CDATA #IMPLIED Type CDATA #IMPLIED Unit CDATA #IMPLIED>
<!ELEMENT Array (Dim*,Stream?)>
<!ATTLIST Array Name CDATA #IMPLIED Type CDATA #IMPLIED>
<!ELEMENT Dim (#PCDATA)>
<!ATTLIST Dim Name CDATA #IMPLIED>
<!ELEMENT Stream (#PCDATA)>
<!ATTLIST Stream Name CDATA #IMPLIED Type (Remote|Local) "Local"
          Delimiter CDATA "," Encoding CDATA #IMPLIED Content CDATA #IMPLIED>
<!ELEMENT Time (#PCDATA)>
<!ATTLIST Time Name CDATA #IMPLIED Type (GPS|Unix|ISO-8601) "ISO-8601">
]>
"""
KINDS = {"TF": "swept sine", "CSD": "FFT"}
"""dttxml's result types that hold transfer functions, and the measurement each comes from."""


@dataclass(frozen=True)
class Transfer:
    """One transfer function ``numerator/denominator`` (diaggui's B/A) of a measurement.

    Attributes
    ----------
    numerator, denominator : str
        Channel names (B and A).
    frequency_hz, tf, coherence : ndarray
        The points (swept sine) or bins (FFT), the complex ratio and its magnitude-squared
        coherence.
    averages : int
    kind : str
        ``"swept sine"`` or ``"FFT"``.
    source : str
        The file it was read from.
    gps : float or None
        The measurement's start (GPS seconds), when the file has it.
    """

    numerator: str
    denominator: str
    frequency_hz: NDArray[np.float64]
    tf: NDArray[np.complex128]
    coherence: NDArray[np.float64]
    averages: int
    kind: str
    source: str
    gps: float | None = None

    @property
    def name(self) -> str:
        """``B/A`` as diaggui labels it."""
        return f"{self.numerator}/{self.denominator}"

    def sigma(self) -> NDArray[np.float64]:
        """Standard error of the real and of the imaginary part of each point, from its
        coherence and the averages (Bendat & Piersol): swept sine and FFT alike."""
        g2 = np.clip(self.coherence, 1e-12, 1.0)
        return np.abs(self.tf) * np.sqrt((1 - g2) / (2 * self.averages * g2))

    def band(self, lo: float, hi: float) -> Transfer:
        """The points from `lo` to `hi` Hz.

        Parameters
        ----------
        lo, hi : float
            The band's edges (Hz), both kept.

        Returns
        -------
        Transfer

        Raises
        ------
        TFError
            If no point lies in the band.
        """
        keep = (self.frequency_hz >= lo) & (self.frequency_hz <= hi)
        if not keep.any():
            msg = (f"{self.name}: no point in {lo:g}-{hi:g} Hz; measured "
                   f"{self.frequency_hz.min():g}-{self.frequency_hz.max():g} Hz")
            raise TFError(msg)
        return replace(self, frequency_hz=self.frequency_hz[keep], tf=self.tf[keep],
                       coherence=self.coherence[keep])

    def to_json(self) -> dict:
        """The ``twind tf --json`` object of one transfer function."""
        return {"numerator": self.numerator, "denominator": self.denominator,
                "kind": self.kind, "averages": self.averages, "source": self.source,
                "frequency_hz": self.frequency_hz.tolist(),
                "tf": {"re": self.tf.real.tolist(), "im": self.tf.imag.tolist()},
                "coherence": self.coherence.tolist(), "sigma": self.sigma().tolist()}

    def lines(self) -> list[str]:
        """A table for a person: one row per point."""
        head = (f"{self.name} ({self.kind}, {self.averages} averages, {len(self.frequency_hz)} "
                f"points, {self.source})")
        rows = [f"{'f [Hz]':>12} {'re':>12} {'im':>12} {'|H|':>11} {'phase [deg]':>11} "
                f"{'coherence':>9} {'sigma':>10}"]
        for f, h, g2, s in zip(self.frequency_hz, self.tf, self.coherence, self.sigma(),
                               strict=True):
            rows.append(f"{f:12.5g} {h.real:12.5g} {h.imag:12.5g} {abs(h):11.4g} "
                        f"{np.degrees(np.angle(h)):11.2f} {g2:9.4f} {s:10.3g}")
        return [head, *rows]


def read_transfers(path: str | Path) -> list[Transfer]:
    """Every transfer function measured in a diaggui file (swept sine or FFT).

    Channel A of each result is the denominator; where some A channels are excitations
    (named ``..._EXC``), only their results are kept, as diaggui shows them. References
    stored in the file (``(REF n)``) are left out.

    Raises
    ------
    TFError
        If the file is not a readable diaggui XML file or holds no transfer function.
    """

    try:
        acc = dttxml.DiagAccess(str(path))
        results = {kind: acc.results[kind] for kind in KINDS if kind in acc.results}
    except Exception as err:  # noqa: BLE001 - dttxml raises many kinds on a bad file
        msg = f"{path}: not a readable diaggui XML file ({type(err).__name__}: {err})"
        raise TFError(msg) from None
    pairs = [(kind, str(r.channelA), str(b)) for kind, found in results.items()
             for key, r in found.items() if "(REF" not in key
             for b in r.channelB if str(b) != str(r.channelA)]
    excited = [p for p in pairs if p[1].endswith("_EXC")]
    transfers = []
    for kind, a, b in dict.fromkeys(excited or pairs):
        x = acc.xfer(b, a)
        transfers.append(Transfer(b, a, np.asarray(x.FHz, dtype=float),
                                  np.asarray(x.xfer, dtype=complex),
                                  np.asarray(x.coh, dtype=float), int(x.averages), KINDS[kind],
                                  str(path), x.gps_second))
    if not transfers:
        msg = f"{path}: no transfer function in it (a diaggui file of spectra only?)"
        raise TFError(msg)
    return transfers


HANN = 1  # diaggui's window code for Hann
_ENBW_BINS = 1.5  # Hann's equivalent noise bandwidth, in bins (diaggui's "BW")


def _param(name: str, kind: str, value: object, unit: str | None = None) -> str:
    unit_attr = f' Unit="{unit}"' if unit else ""
    return f'    <Param Name="{name}" Type="{kind}"{unit_attr}>{escape(str(value))}</Param>\n'


def _stream(values: NDArray) -> str:
    text = base64.encodebytes(np.ascontiguousarray(values).astype(values.dtype.newbyteorder("<"))
                              .tobytes()).decode()
    return f'      <Stream Encoding="LittleEndian,base64">\n{text}      </Stream>\n'


def _result(k: int, subtype: int, f: NDArray, gps: float, rate: float, averages: int,
            a: str, bs: Sequence[str], kind: str, values: NDArray) -> str:
    out = [f'  <LIGO_LW Name="Result[{k}]" Type="Spectrum">\n', _param("Flag", "string", "Result"),
           _param("Subtype", "int", subtype), _param("f0", "double", f[0], "Hz"),
           _param("df", "double", f[1] - f[0], "Hz"),
           f'    <Time Name="t0" Type="GPS">{gps}</Time>\n',
           _param("dt", "double", 1.0 / rate, "s"),
           _param("BW", "double", _ENBW_BINS * (f[1] - f[0]), "Hz"),
           _param("Window", "int", HANN), _param("AverageType", "int", 0),
           _param("Averages", "int", averages), _param("N", "int", f.size),
           _param("M", "int", max(len(bs), 1)), _param("ChannelA", "string", a, "channel")]
    out += [_param(f"ChannelB[{i}]", "string", b, "channel") for i, b in enumerate(bs)]
    out += [f'    <Array Type="{kind}">\n      <Dim>{values.size}</Dim>\n', _stream(values),
            "    </Array>\n  </LIGO_LW>\n"]
    return "".join(out)


def write_fft_measurement(path: str | Path, exc: str, channels: Sequence[str],
                          frequency_hz: NDArray[np.float64], exc_psd: NDArray[np.float64],
                          tf: NDArray[np.complex128], coherence: NDArray[np.float64],
                          averages: int, rate_hz: float = 16384.0, gps: float = 1.4e9,
                          overlap: float = 0.5) -> Path:
    """Write one excitation's FFT measurement as diaggui saves it.

    Parameters
    ----------
    path : str or Path
        File to create; an existing file is refused.
    exc : str
        Channel A, e.g. ``C1:SUS-ETMX_SUSPOS_EXC``.
    channels : sequence of str
        Channels B (IN1, IN2, OUT of each DOF).
    frequency_hz : ndarray, shape (nf,)
        Evenly spaced from ``f0``.
    exc_psd : ndarray, shape (nf,)
        One-sided PSD of the excitation.
    tf, coherence : ndarray, shape (len(channels), nf)
        ``B/A`` and its magnitude-squared coherence.
    averages : int
    rate_hz, gps, overlap : float
        Recorded in the file's parameters.

    Returns
    -------
    Path
    """
    path = Path(path)
    if path.exists():
        msg = f"{path} exists; twind does not overwrite measurements"
        raise TFError(msg)
    f = np.asarray(frequency_hz, dtype=float)
    tf = np.atleast_2d(tf)
    coherence = np.atleast_2d(coherence)
    if tf.shape != (len(channels), f.size) or coherence.shape != tf.shape:
        msg = (f"need tf and coherence of shape {(len(channels), f.size)}, got {tf.shape} "
               f"and {coherence.shape}")
        raise TFError(msg)
    # the file holds the conjugate of scipy's CSD(A, B), which dttxml's xfer(B, A) conjugates
    # back; a round trip of example_null checks it (tests/test_tf.py)
    csd = np.conj(tf) * exc_psd
    with np.errstate(divide="ignore", invalid="ignore"):
        psd_b = np.where(coherence > 0, np.abs(csd) ** 2 / (coherence * exc_psd), 0.0)
    asds = np.sqrt(np.vstack([exc_psd, np.nan_to_num(psd_b)]))
    names = [exc, *channels]
    parts = [_DTD, '<LIGO_LW Name="Diagnostics Test">\n', _header(gps),
             _test(exc, names, f, averages, overlap, rate_hz),
             _index(exc, names, len(f))]
    for k, (name, asd) in enumerate(zip(names, asds, strict=True)):
        parts.append(_result(k, 1, f, gps, rate_hz, averages, name, [], "float",
                             asd.astype(np.float32)))
    n = len(names)
    parts.append(_result(n, 2, f, gps, rate_hz, averages, exc, channels, "floatComplex",
                         csd.astype(np.complex64).reshape(-1)))
    parts.append(_result(n + 1, 3, f, gps, rate_hz, averages, exc, channels, "float",
                         coherence.astype(np.float32).reshape(-1)))
    parts.append("</LIGO_LW>\n")
    path.write_text("".join(parts))
    return path


def _header(gps: float) -> str:
    return ('  <LIGO_LW Name="Header" Type="Global">\n'
            + _param("Flag", "string", "TestParameters")
            + _param("Creator", "string", "twind")
            + _param("TestType", "string", "FFT")
            + f'    <Time Name="TestTime" Type="GPS">{gps}</Time>\n'
            + "  </LIGO_LW>\n")


def _test(exc: str, names: list[str], f: NDArray, averages: int, overlap: float,
          rate: float) -> str:
    out = ['  <LIGO_LW Name="Test" Type="TestParameter">\n',
           _param("Flag", "string", "TestParameters"), _param("Subtype", "string", "FFT"),
           _param("StartFrequency", "double", f[0], "Hz"),
           _param("StopFrequency", "double", f[-1], "Hz"),
           _param("BW", "double", f[1] - f[0], "Hz"), _param("Overlap", "double", overlap),
           _param("Window", "int", HANN), _param("RemoveDC", "boolean", "true"),
           _param("AverageType", "int", 0), _param("Averages", "int", averages),
           _param("StimulusType[0]", "int", 3),
           _param("StimulusChannel[0]", "string", exc, "channel"),
           _param("StimulusActive[0]", "boolean", "true")]
    for i, name in enumerate(names):
        out += [_param(f"MeasurementChannelRate[{i}]", "int", int(rate)),
                _param(f"MeasurementChannel[{i}]", "string", name, "channel"),
                _param(f"MeasurementActive[{i}]", "boolean", "true")]
    return "".join(out) + "  </LIGO_LW>\n"


def _index(exc: str, names: list[str], nf: int) -> str:
    n = len(names)
    power = "".join(f"      Channel[{i}] = {c};\n      Name[{i}] = Result[{i}];\n"
                    f"      Offset[{i}] = 0;\n      Length[{i}] = {nf};\n"
                    for i, c in enumerate(names))

    def pairs(result: int) -> str:
        return "".join(f"      ChannelA[0] = {exc};\n      ChannelB[0][{j}] = {c};\n"
                       f"      Name[0][{j}] = Result[{result}];\n"
                       f"      Offset[0][{j}] = {j * nf};\n      Length[0][{j}] = {nf};\n"
                       for j, c in enumerate(names[1:]))

    entries = ["MasterIndex:\n      Entry[0] = MasterIndex;\n      Entry[1] = PowerSpectrum[0];\n"
               "      Entry[2] = CrossCorrelation[0];\n      Entry[3] = Coherence[0];",
               "PowerSpectrum[0]:\n" + power.rstrip("\n"),
               "CrossCorrelation[0]:\n" + pairs(n).rstrip("\n"),
               "Coherence[0]:\n" + pairs(n + 1).rstrip("\n")]
    return ('  <LIGO_LW Name="Index" Type="Index">\n' + _param("Flag", "string", "Result")
            + "".join(_param(f"Entry[{i}]", "string", e) for i, e in enumerate(entries))
            + "  </LIGO_LW>\n")


def write_measurement_set(tfs: TFSet, directory: str | Path, ifo: str = "C1",
                          rate_hz: float = 16384.0, gps: float = 1.4e9,
                          stop_hz: float | None = None) -> list[Path]:
    """One diaggui file per excited DOF of `tfs` (``<OPTIC>_<DOF>_exc.xml``, as
    example_null), for TFs whose excitation PSD is known (``tfs.exc_psd``); with `stop_hz`,
    the bins up to it alone, as diaggui keeps its StopFrequency (example_null: 30 Hz).

    Parameters
    ----------
    tfs : TFSet
        The measurement, with its excitation PSDs.
    directory : str or Path
        Where the files go (made if missing).
    ifo : str
        The interferometer prefix of the channel names (``C1``).
    rate_hz : float
        Sample rate (Hz) recorded for every channel.
    gps : float
        GPS start time recorded in the files.
    stop_hz : float, optional
        The last frequency (Hz) written; default every bin.

    Returns
    -------
    list of Path
        One file per excited DOF.

    Raises
    ------
    TFError
        If `tfs` carries no excitation PSD, or a file exists already.
    """

    if not tfs.exc_psd:
        msg = "these TFs carry no excitation PSD (measure them with twind's own tools)"
        raise TFError(msg)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    keep = slice(None) if stop_hz is None else tfs.frequency_hz <= stop_hz
    out = []
    for j, dof in enumerate(tfs.excited):
        keys = [(r, p) for r in tfs.responses for p in POINTS]
        chans = [f"{ifo}:SUS-{tfs.optic}_SUS{r}_{p}" for r, p in keys]
        tf = np.array([tfs.tf[p][keep, tfs.responses.index(r), j] for r, p in keys])
        coh = np.array([tfs.coherence[p][keep, tfs.responses.index(r), j] for r, p in keys])
        out.append(write_fft_measurement(
            directory / f"{tfs.optic}_{dof}_exc.xml", f"{ifo}:SUS-{tfs.optic}_SUS{dof}_EXC",
            chans, tfs.frequency_hz[keep], tfs.exc_psd[dof][keep], tf, coh, tfs.averages,
            rate_hz, gps))
    return out
