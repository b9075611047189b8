"""An independent expert reading of KAGRA's real suspension measurements against KAGRA's own
state-space models: the yardstick twind's analysis of the same files is held to.

It shares no code with twind's model or analysis: the diaggui files are read with dttxml, the
models' responses are computed from the ``.mat`` matrices with numpy and scipy, and every step
(coherent bands, resonance fits, the model's visible modes, their correspondence, the
calibration, delay and unmodelled couplings) is done here from first principles, so that an
error in twind cannot hide in its own reference.

Run ``python -m twind.lab.kagra_reference -o DIR [FILES...]`` (default: the five files of
``tests/data/kagra/``): it writes ``DIR/<file>.json`` and ``DIR/<file>.png`` and prints a
table. ``tests/data/kagra/reference.toml`` is the hand-curated answer key made from them.
"""

from __future__ import annotations

import json
import math
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import dttxml
import numpy as np
import scipy.io
from matplotlib.figure import Figure
from numpy.typing import NDArray
from scipy import linalg, optimize, signal

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data" / "kagra"
MODELS = ROOT / "twind" / "configs" / "kagra"
FILES = ("SRM_TMP_200722.xml", "BS_TML_exc_20200730a.xml", "BS_TML_exc_20200730b.xml",
         "BS_TMP_exc_20200730a.xml", "BS_TMP_exc_20200730b.xml")
"""The real measurements shared in ``tests/data/kagra/``."""
DRIVES = {f"TM_{kind}_{d}": f"exc_TM{d}" for kind in ("TEST", "LOCK") for d in "LPY"}
"""Excitation test point (without ``_EXC``) -> the model input it drives."""
READBACKS = {f"IM_DAMP_{d}_IN1": f"OSEM_IM{d}" for d in "LTVRPY"} | {
    "TM_OPLEV_PIT_DIAG": "OpLev_TMP", "TM_OPLEV_YAW_DIAG": "OpLev_TMY",
    "TM_OPLEV_LEN_DIAG": "OpLev_TML"} | {f"{x}_DAMP_GAS_IN1": f"LVDT_{x}GAS" for x in
                                         ("F0", "F1", "BF")}
"""Readback channel suffix -> the model output it reads."""
MAIN = {"exc_TMP": "TM_OPLEV_PIT_DIAG", "exc_TML": "TM_OPLEV_LEN_DIAG",
        "exc_TMY": "TM_OPLEV_YAW_DIAG"}
"""The readback collocated with each drive, which couplings are compared with."""
NOT_MODELLED = 1e-6
"""An element whose model response is below this fraction of both the readback's largest
response to any excitation and the drive's largest at any sensor is the model's numerical
noise (its symmetric cross-couplings sit near 1e-10)."""
SMEAR_BINS = 0.75
"""Half width (bins) of the damping that shows the model at the measurement's resolution:
a Hann window's equivalent noise bandwidth is 1.5 bins."""
RESOLVED_BINS = 2.0
"""A fitted peak narrower than this many bins is the Hann window's smear of a line narrower
than a bin (a synthetic Q of 160 at 0.75 Hz fits 1.4 bins wide): its Q is only bounded."""
COHERENT_RUN = 5
"""An element is coherent when a run of this many bins is: chance runs in the readbacks no
drive reaches (the GAS filters') are four bins long at most in these files."""
SIGNIFICANT = 30.0
"""The least a resonance must lower its window's chi-square against a straight background,
in units of its fit's residual variance (spurious fits in noise reach 20)."""
MIN_HEIGHT = 0.25
"""A fitted resonance standing less than this over its background is not a peak."""
NONE_COST = 3.0
"""The cost past which a measured mode is better left without a model counterpart: a 60 %
shift of a matching pattern, or a 15 % shift of a half-matching one."""


# --- the measurement and the model -----------------------------------------------------------

@dataclass
class Element:
    """One readback of one drive: the measured transfer function and what is found in it."""

    name: str
    output: str
    f: NDArray[np.float64]
    h: NDArray[np.complex128]
    coh: NDArray[np.float64]
    model: NDArray[np.complex128] | None = None
    ratios: tuple[float, float] = (0.0, 0.0)
    info: dict = field(default_factory=dict)

    @property
    def modelled(self) -> bool:
        """Whether the model couples the drive to this readback above its numerical noise."""
        return max(self.ratios) >= NOT_MODELLED


def read_elements(path: Path) -> tuple[str, str, list[Element], int]:
    """Every known readback of the file's excitation (``<IFO>:VIS-<OPTIC>_<drive>_EXC``),
    the DC bin dropped.

    Returns
    -------
    optic, drive : str
        The optic (``SRM``) and the model input the excitation drives (``exc_TMP``).
    list of Element
    int
        The number of averages.
    """
    access = dttxml.DiagAccess(str(path))
    present = access.channels()[0]
    hits = [m for n in sorted(present) if (m := re.fullmatch(r"(\w+):VIS-([A-Z0-9]+)_(\w+)_EXC",
                                                              n)) and m.group(3) in DRIVES]
    if not hits:
        msg = f"{path.name}: no excitation of {sorted(DRIVES)}"
        raise ValueError(msg)
    ifo, optic, drive = hits[0].group(1), hits[0].group(2), DRIVES[hits[0].group(3)]
    elements, averages = [], 0
    for suffix, output in READBACKS.items():
        if (channel := f"{ifo}:VIS-{optic}_{suffix}") in present:
            x = access.xfer(channel, hits[0].group(0))
            f = np.asarray(x.FHz, dtype=float)
            keep, averages = f > 0, int(x.averages)
            elements.append(Element(suffix, output, f[keep], np.asarray(x.xfer)[keep].astype(
                complex), np.clip(np.asarray(x.coh, dtype=float)[keep], 0.0, 1.0)))
    return optic, drive, elements, averages


@dataclass
class Model:
    """A continuous-time state-space model with named inputs and outputs, its responses
    computed through the complex Schur form ``A = Z T Z^H``: one back-substitution per
    frequency, exact however close or defective the poles."""

    a: NDArray[np.float64]
    b: NDArray[np.float64]
    c: NDArray[np.float64]
    d: NDArray[np.float64]
    inputs: list[str]
    outputs: list[str]

    def __post_init__(self) -> None:
        self._t, self._z = linalg.schur(np.asarray(self.a, dtype=complex), output="complex")

    def response(self, f_hz: NDArray[np.float64], inputs: Sequence[str],
                 outputs: Sequence[str], damping: float = 0.0) -> NDArray[np.complex128]:
        """``H(s)`` at ``s = damping + 2 pi i f``, shape ``(nf, n_outputs, n_inputs)``; a
        positive `damping` (rad/s) sees every pole that much more damped (a resolution)."""
        ii = [self.inputs.index(n) for n in inputs]
        oo = [self.outputs.index(n) for n in outputs]
        y, cz, n = self._z.conj().T @ self.b[:, ii], self.c[oo, :] @ self._z, self._t.shape[0]
        out = np.empty((len(f_hz), len(oo), len(ii)), dtype=complex)
        for lo in range(0, len(f_hz), 4096):
            s = damping + 2j * np.pi * np.asarray(f_hz[lo:lo + 4096])
            x = np.empty((n, s.size, len(ii)), dtype=complex)
            for i in range(n - 1, -1, -1):
                acc = np.tensordot(self._t[i, i + 1:], x[i + 1:], axes=(0, 0)) + y[i]
                x[i] = acc / (s - self._t[i, i])[:, None]
            out[lo:lo + 4096] = np.einsum("on,nfi->foi", cz, x) + self.d[np.ix_(oo, ii)]
        return out

    @property
    def poles(self) -> NDArray[np.complex128]:
        """The eigenvalues of ``A`` (rad/s)."""
        return np.diag(self._t)


def load_model(optic: str) -> Model:
    """KAGRA's open-loop model of `optic` (``twind/configs/kagra/<optic>_safe.mat``), its
    names without the Simulink prefix before ``/``."""
    ss = scipy.io.loadmat(str(MODELS / f"{optic}_safe.mat"), squeeze_me=True,
                          struct_as_record=False)["linss"]
    mats = [np.atleast_2d(m).astype(float) for m in (ss.a, ss.b, ss.c, ss.d)]
    return Model(*mats, *([str(n).split("/")[-1] for n in np.atleast_1d(names)]
                          for names in (ss.InputName, ss.OutputName)))


def attach_model(model: Model, drive: str, elements: list[Element]) -> NDArray[np.float64]:
    """Give each element the model's response on its bins (``model``), smeared to the
    measurement's resolution on a quarter-bin grid (``info["fine"]``, ``info["grid"]``)
    and its two above-noise ratios (``ratios``, :data:`NOT_MODELLED`).

    Returns
    -------
    ndarray
        The quarter-bin grid.
    """
    f, df = elements[0].f, elements[0].f[1] - elements[0].f[0]
    outputs, smear = [e.output for e in elements], 2 * np.pi * SMEAR_BINS * df
    excs = sorted({drive, *(n for n in model.inputs if n.startswith("exc_"))})
    sensors = [n for n in model.outputs if n.split("_")[0] in ("OSEM", "OpLev", "LVDT", "GEO")]
    coarse = np.geomspace(f[0], f[-1], 2000)
    peak_in = np.abs(model.response(coarse, excs, outputs, smear)).max(axis=0)
    peak_out = np.abs(model.response(coarse, [drive], sensors, smear)).max()
    j = excs.index(drive)
    fine = np.arange(df / 4, f[-1] + df / 8, df / 4)
    smeared = model.response(fine, [drive], outputs, smear)[:, :, 0]
    exact = model.response(f, [drive], outputs)[:, :, 0]
    for k, e in enumerate(elements):
        e.ratios = (float(peak_in[k, j] / max(peak_in[k].max(), 1e-300)),
                    float(peak_in[k, j] / max(peak_out, 1e-300)))
        e.model, e.info["fine"], e.info["grid"] = exact[:, k], smeared[:, k], fine
    return fine


# --- coherent bands and measured peaks -------------------------------------------------------

def coherent_mask(coh: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Bins whose coherence is at least 0.5 after a 5-bin running mean, or 0.9 alone."""
    return (np.convolve(coh, np.ones(5) / 5, mode="same") >= 0.5) | (coh >= 0.9)


def runs(mask: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """The ``[start, stop)`` index ranges where `mask` holds."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int), [0]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def relative_error(coh: NDArray[np.float64], averages: int) -> NDArray[np.float64]:
    """A transfer function estimate's relative standard error from its coherence (Bendat
    and Piersol), the coherence smoothed over 5 bins, freed of its bias over few averages
    (``(n g - 1)/(n - 1)``) and kept within [0.1, 0.995]."""
    g = np.convolve(coh, np.ones(5) / 5, mode="same")
    g = np.clip((averages * g - 1) / (averages - 1), 0.1, 0.995)
    return np.sqrt((1 - g) / (2 * averages * g))


def candidates(e: Element, mask: NDArray[np.bool_], err: NDArray[np.float64]) -> list[int]:
    """Peaks of ``|H|`` near a coherent run (within 20 bins), standing out of their local
    background by four times the flanks' scatter (and by 25 % at least).

    The prominence is taken on ``|H|`` bridged over the incoherent bins, so that a bin whose
    coherence dips (noise, or a notch) makes no peak and no base; the top of a high-Q peak,
    where the mode's ambient motion may swamp the drive, is carried by its coherent flanks
    and found again as the largest bin within four of theirs.
    """
    good = np.flatnonzero(mask)
    if good.size < 2:
        return []
    logh = np.interp(np.arange(e.f.size), good, np.log(np.abs(e.h[good]) + 1e-300))
    df, out = e.f[1] - e.f[0], set()
    for i in signal.find_peaks(logh)[0]:
        near = runs(mask[max(i - 20, 0):i + 21])
        if i < 6 or not any(b - a >= COHERENT_RUN for a, b in near):
            continue
        prom = signal.peak_prominences(logh, [i], wlen=2 * max(10, int(0.15 * e.f[i] / df)) + 1)
        noise = np.median(err[np.r_[max(i - 6, 0):i - 1, i + 2:min(i + 7, e.f.size)]])
        if prom[0][0] >= max(math.log(1.25), 4 * noise):
            out.add(int(i - 4 + np.argmax(np.abs(e.h[i - 4:i + 5]))))
    return sorted(out)


def _resonance(p: NDArray[np.float64], f: NDArray[np.float64], f_ref: float,
               width: float) -> NDArray[np.complex128]:
    """A second-order section of peak value ``A`` at ``f0`` over a linear complex background;
    ``p = (f0, ln Q, Re A, Im A, Re a, Im a, Re b, Im b)``."""
    f0, q = p[0], math.exp(p[1])
    section = (1j / q) / (1 - (f / f0) ** 2 + 1j * f / (f0 * q))
    return (p[2] + 1j * p[3]) * section + p[4] + 1j * p[5] + (p[6] + 1j * p[7]) * (
        f - f_ref) / width


def fit_peak(e: Element, err: NDArray[np.float64], i: int, half: int,
             width: float) -> dict | None:
    """Least-squares fit of one resonance at bin `i` over ``i +- half`` bins, residuals
    weighted by the estimate's scatter; ``sigma_f`` from the Jacobian, scaled by the
    residuals' own scatter. None when the fit fails, drifts off, finds no maximum near
    ``f0`` (a notch or a coherence dip fitted as a pole) or is not :data:`SIGNIFICANT`."""
    lo, hi = max(i - half, 0), min(i + half + 1, e.f.size)
    f, y, f_ref, df = e.f[lo:hi], e.h[lo:hi] / abs(e.h[i]), e.f[i], e.f[1] - e.f[0]
    w = 1 / (np.abs(y) * err[lo:hi] + 1e-3)
    base = 0.5 * (y[0] + y[-1])
    top = y[i - lo] - base
    q_max = f_ref / df  # the Hann window smears a line over more than a bin
    p0 = [f_ref, min(math.log(max(f_ref / width, 1.6)), math.log(q_max) - 1e-6), top.real,
          top.imag, base.real, base.imag, 0.0, 0.0]
    bounds = ([f[0], 0.0, *[-np.inf] * 6], [f[-1], math.log(q_max), *[np.inf] * 6])

    def resid(p: NDArray[np.float64]) -> NDArray[np.float64]:
        r = (_resonance(p, f, f_ref, width) - y) * w
        return np.concatenate([r.real, r.imag])

    dof = 2 * f.size - 8
    try:
        fit = optimize.least_squares(resid, p0, bounds=bounds, x_scale="jac")
        chi2 = float(np.sum(fit.fun ** 2)) / dof
        cov = np.linalg.pinv(fit.jac.T @ fit.jac) * chi2
    except (ValueError, np.linalg.LinAlgError, ZeroDivisionError):
        return None
    p, grid = fit.x, np.linspace(f[0], f[-1], 200)
    f0, q = float(p[0]), math.exp(p[1])
    at = grid[int(np.argmax(np.abs(_resonance(p, grid, f_ref, width))))]
    if (not fit.success or abs(at - f0) > max(f0 / q, 2 * df) or q < 1.5
            or abs(f0 - f_ref) > max(0.5 * f0 / q, 2 * df) or f0 / q > f[-1] - f[0]):
        return None
    line = np.vstack([np.ones_like(f), (f - f_ref) / width]).T * w[:, None]
    chi2_bg = np.sum(np.abs(line @ np.linalg.lstsq(line, y * w, rcond=None)[0] - y * w) ** 2)
    significance = float(chi2_bg - chi2 * dof) / chi2
    bg = abs(complex(p[4], p[5]) + complex(p[6], p[7]) * (f0 - f_ref) / width)
    return None if significance < SIGNIFICANT else {
        "f": f0, "sigma_f": float(math.sqrt(max(cov[0, 0], 0.0))), "Q_fit": q,
        "Q": q if f0 / q >= RESOLVED_BINS * df else "not resolved",
        "Q_min": f0 / (RESOLVED_BINS * df), "sigma_lnQ": float(math.sqrt(max(cov[1, 1], 0.0))),
        "fwhm": f0 / q,
        "height": abs(complex(p[2], p[3])) / max(bg, 1e-12), "chi2": chi2,
        "significance": significance, "resolved": bool(f0 / q >= RESOLVED_BINS * df),
        "coherence": float(e.coh[max(i - 1, 0):i + 2].mean())}


def element_peaks(e: Element, mask: NDArray[np.bool_], averages: int) -> list[dict]:
    """Every resonance peak of a coherent element, fitted twice (the second window from the
    first fit's width, 2.5 widths and four coherent bins each side at least); by frequency.
    """
    err, df = relative_error(e.coh, averages), e.f[1] - e.f[0]
    found, peaks = candidates(e, mask, err), []
    for i in found:
        room = min([abs(i - j) for j in found if j != i] + [10 ** 6])
        level, lo, hi = abs(e.h[i]) / math.sqrt(2), i, i  # the half-power width
        while lo > max(i - 200, 0) and abs(e.h[lo - 1]) > level:
            lo -= 1
        while hi < min(i + 200, e.f.size - 1) and abs(e.h[hi + 1]) > level:
            hi += 1
        width, fit = (hi - lo + 1) * df, None
        for _ in range(2):
            half = min(max(4, math.ceil(2.5 * width / df)), max(room - 1, 4))
            while half < 40 and min(mask[max(i - half, 0):i].sum(),
                                    mask[i + 1:i + half + 1].sum()) < 4:
                half += 1
            if (fit := fit_peak(e, err, i, half, width)) is None:
                break
            width = max(fit["fwhm"], df)
        if (fit is not None and fit["height"] >= MIN_HEIGHT and fit["sigma_f"] <= max(
                fit["fwhm"], df) and all(abs(fit["f"] - p["f"]) >= max(
                df, 0.5 * min(fit["fwhm"], p["fwhm"])) for p in peaks)):
            peaks.append(fit)
    return sorted(peaks, key=lambda p: p["f"])


# --- the model's peaks -----------------------------------------------------------------------

def model_modes(model: Model, drive: str, elements: list[Element],
                fine: NDArray[np.float64]) -> list[dict]:
    """The model's pole pairs showing as peaks in its response at the measurement's
    resolution, with the modelled elements each shows in and its height there (peak over
    base): each local maximum of the smeared response standing 25 % out of its surroundings
    is the pole pair within two bins whose own term is the largest there (the residue
    ``|H(i w_k)| |Re lambda_k|`` over its smeared half width)."""
    df = elements[0].f[1] - elements[0].f[0]
    lam = model.poles[(model.poles.imag > 1e-9) & (model.poles.imag < 2 * np.pi * fine[-1])]
    at = model.response(lam.imag / (2 * np.pi), [drive], [e.output for e in elements])[:, :, 0]
    modes: dict[int, dict] = {}
    for k, e in enumerate(elements):
        idx, props = signal.find_peaks(np.log(np.abs(e.info["fine"]) + 1e-300), prominence=math.log(
            1.25), wlen=2 * int(0.25 / (fine[1] - fine[0])) + 1) if e.modelled else ([], {})
        for i, prom in zip(idx, props.get("prominences", []), strict=True):
            near = np.flatnonzero(np.abs(lam.imag / (2 * np.pi) - fine[i]) <= 2 * df)
            if near.size:
                share = np.abs(at[near, k] * lam[near].real) / np.maximum(
                    np.abs(lam[near].real), 2 * np.pi * SMEAR_BINS * df)
                j = int(near[np.argmax(share)])
                mode = modes.setdefault(j, {"f": float(abs(lam[j]) / (2 * np.pi)), "Q": float(
                    abs(lam[j]) / (-2 * lam[j].real)), "label": label(model, lam[j]),
                                            "elements": {}})
                mode["elements"][e.name] = {"f_peak": float(fine[i]),
                                            "height": float(math.exp(prom))}
    return sorted(modes.values(), key=lambda m: m["f"])


COLLOCATED = {f"{body} {d}": (f"{pre}{body}{d}", f"{out}{body}{d}") for body, pre, out in (
    ("TM", "f_", "disp"), ("IM", "exc_", "OSEM_")) for d in "LTVRPY"} | {
    f"{x} GAS": (f"exc_{x}GAS", f"LVDT_{x}GAS") for x in ("F0", "F1", "BF")} | {
    f"IP {d}": (f"exc_IP{d}", f"LVDT_IP{d}") for d in "LTY"}
"""A DOF -> the model input and output collocated on it."""


def label(model: Model, lam: complex) -> str:
    """The DOF carrying the largest share of a pole pair's static compliance at the
    collocated pairs, ``2 |H_dd(i w)| |Re lambda| / (w |H_dd(0)|)`` (``H_dd(0)`` at 1e-4
    Hz: the models hold integrators whose gains are zero); empty without such pairs."""
    pairs = [(k, i, o) for k, (i, o) in COLLOCATED.items()
             if i in model.inputs and o in model.outputs]
    if not pairs:
        return ""
    h = model.response(np.array([1e-4, lam.imag / (2 * np.pi)]), [i for _, i, _ in pairs],
                       [o for _, _, o in pairs])
    share = [2 * abs(h[1, n, n] * lam.real) / (abs(lam) * max(abs(h[0, n, n]), 1e-300))
             for n in range(len(pairs))]
    return pairs[int(np.argmax(share))][0]


def short(name: str) -> str:
    """A readback's short label: ``IM_DAMP_P_IN1`` -> ``IM_P``, ``TM_OPLEV_PIT_DIAG`` ->
    ``OL_PIT``, ``F0_DAMP_GAS_IN1`` -> ``GAS_F0``."""
    parts = name.split("_")
    return {"IM": "IM_" + parts[2], "TM": "OL_" + parts[2]}.get(parts[0], "GAS_" + parts[0])


# --- measured modes and their correspondence -------------------------------------------------

def group_modes(peaks: dict[str, list[dict]], df: float) -> list[dict]:
    """Gather the elements' peaks into measured modes: peaks within a bin and a half (or
    their narrower width) of each other, one per element. A mode's frequency is the peaks'
    weighted mean, its sigma the larger of the best single fit's and the mean's scaled by
    the peaks' scatter (the elements see one mode ringing in one ambient field: their
    errors are not independent)."""
    groups: list[list[tuple]] = []
    for item in sorted(((p["f"], n, p) for n, ps in peaks.items() for p in ps),
                       key=lambda t: t[0]):
        if groups and item[1] not in {n for _, n, _ in groups[-1]} and item[0] - groups[-1][
                -1][0] <= max(1.5 * df, min(item[2]["fwhm"], groups[-1][-1][2]["fwhm"])):
            groups[-1].append(item)
        else:
            groups.append([item])
    modes = []
    for g in groups:
        f = np.array([p["f"] for _, _, p in g])
        w = 1 / np.array([max(p["sigma_f"], 1e-6) for _, _, p in g]) ** 2
        mean = float(np.sum(w * f) / w.sum())
        scatter = float(np.sum(w * (f - mean) ** 2) / max(len(g) - 1, 1))
        best = min(g, key=lambda t: t[2]["sigma_f"])[2]
        modes.append({"f": mean, "sigma_f": max(best["sigma_f"], math.sqrt(
            max(scatter, 1.0) / w.sum())), "Q": best["Q"], "Q_min": best["Q_min"],
                      "resolved": best["resolved"],
                      "elements": {n: {k: p[k] for k in ("f", "sigma_f", "height",
                                                          "significance")} for _, n, p in g}})
    return modes


def _relative(heights: list[dict[str, float]]) -> list[dict[str, float]]:
    """Each mode's log height (peak over base) in each element over the largest there: how
    a peak ranks among its element's, which the undamped model and the damped suspension
    share where their absolute heights do not."""
    top: dict[str, float] = {}
    for h in heights:
        for n, v in h.items():
            top[n] = max(top.get(n, 0.0), math.log(max(v, 1.0)))
    return [{n: math.log(max(v, 1.0)) / top[n] for n, v in h.items() if top[n] > 0}
            for h in heights]


def correspond(modes: list[dict], model: list[dict], elements: list[Element],
               poles: list[dict]) -> None:
    """Match each measured mode to the model mode it most plausibly is (``mode["model"]``,
    None when none does): the one-to-one assignment of least total cost, each measured
    mode's costs weighted by its strength squared (its pattern's sum), so that the obvious
    modes are named right first.

    The cost of a pair is its frequency shift in units of 30 % plus twice the mismatch
    (one minus the cosine) of their patterns: their relative log heights (:func:`_relative`)
    over the modelled elements that show the measured mode or are coherent in half the 21
    bins about it, where its absence tells. Shifts past a factor of two, patterns sharing no
    element and costs past :data:`NONE_COST` leave a mode unmatched. A mode standing five
    times higher where the model has no coupling than anywhere it has is a coupling the
    model lacks: it is given the nearest pole pair (within 30 %) of that element's DOF.
    """
    by_name, k_of = {e.name: e for e in elements}, 1 / (elements[0].f[1] - elements[0].f[0])
    cost, strength = np.full((len(modes), len(model)), 1e6), np.zeros(len(modes))
    ours = _relative([{n: 1 + v["height"] for n, v in m["elements"].items()} for m in modes])
    theirs = _relative([{n: v["height"] for n, v in mm["elements"].items()} for mm in model])
    for i, m in enumerate(modes):
        top = max(m["elements"], key=lambda n: m["elements"][n]["height"])
        k = round(m["f"] * k_of) - 1
        names = [n for n, e in by_name.items() if e.modelled and (
            n in m["elements"] or e.info["mask"][max(k - 10, 0):k + 11].mean() >= 0.5)]
        mine = np.array([ours[i].get(n, 0.0) for n in names])
        strength[i] = mine.sum()
        m["model_elements"] = [n for n in names if n in m["elements"]]
        m["coupling"] = max([v["height"] for n, v in m["elements"].items() if by_name[
            n].modelled], default=0.0) < 0.2 * m["elements"][top]["height"]
        for j, mm in enumerate(model):
            them = np.array([theirs[j].get(n, 0.0) for n in names])
            shift, norm = abs(math.log(m["f"] / mm["f"])), np.linalg.norm(mine) * np.linalg.norm(
                them)
            if not m["coupling"] and norm > 0 and shift <= math.log(2) and mine @ them > 0:
                cost[i, j] = shift / math.log(1.3) + 2 * (1 - mine @ them / norm)
        if m["coupling"]:
            dof = (by_name[top].output[5:7] + " GAS" if by_name[top].output.startswith("LVDT")
                   else " " + by_name[top].output[-1])
            near = [p for p in poles if p["label"].endswith(dof)
                    and abs(math.log(m["f"] / p["f"])) < math.log(1.3)]
            m["own_dof_model"] = min(near, key=lambda p: abs(p["f"] - m["f"]), default=None)
    full = strength[:, None] ** 2 * np.hstack([np.minimum(cost, 1e3), np.full(
        (len(modes), len(modes)), NONE_COST)])
    for i, j in zip(*optimize.linear_sum_assignment(full), strict=True):
        m = modes[i]
        m["model"] = None if j >= len(model) or cost[i, j] >= NONE_COST else {
            "f": model[j]["f"], "Q": model[j]["Q"], "label": model[j]["label"],
            "shift_pct": 100 * (m["f"] / model[j]["f"] - 1), "cost": float(cost[i, j])}
        if m["model"] is None:
            m["why_none"] = ("a coupling the model lacks" if m["coupling"]
                             else "no model mode of its pattern")


# --- calibration, delay and couplings --------------------------------------------------------

def clean_bins(e: Element, averages: int) -> NDArray[np.bool_]:
    """The element's coherent bins five widths (and four bins at least) away from every
    measured peak and notch and from every peak and notch of the smeared model."""
    df, keep = e.f[1] - e.f[0], e.info["mask"].copy()
    notches = Element(e.name, e.output, e.f, 1 / (e.h + 1e-300), e.coh)
    away = [(p["f"], 5 * max(p["fwhm"], 1.5 * df)) for p in e.info.get("peaks", [])]
    away += [(e.f[i], 7.5 * df) for i in candidates(notches, keep, relative_error(
        e.coh, averages))]
    for sign in (1, -1):
        idx = signal.find_peaks(sign * np.log(np.abs(e.info["fine"]) + 1e-300),
                                prominence=math.log(1.25))[0]
        away += [(e.info["grid"][i], max(7.5 * df, 0.05 * e.info["grid"][i])) for i in idx]
    for f0, half in away:
        keep &= np.abs(e.f - f0) > max(half, 4 * df)
    return keep


def scale(e: Element, keep: NDArray[np.bool_], tau_s: float = 0.0) -> dict | None:
    """The measured/model ratio an expert reads as the element's calibration.

    Over the clean bins the ratio is flat where both are mechanics and leaves that plateau
    where the suspension has what the model lacks (a sensing floor, a shifted zero): the
    plateau is the densest factor-of-1.5 band of ``|ratio|``, its median the magnitude,
    the circular mean of its lowest fifth (five bins at least), `tau_s` of delay taken
    out, the phase. It is ``reliable`` when the plateau holds ten bins and half the clean
    ones; ``median_all`` is the median over every clean bin.
    """
    if keep.sum() < 5:
        return None
    f, r = e.f[keep], e.h[keep] / e.model[keep]
    lnr = np.log(np.abs(r))
    order = np.sort(lnr)
    counts = np.searchsorted(order, order + 2 * math.log(1.5), side="right")
    start = order[int(np.argmax(counts - np.arange(order.size)))]
    flat = (lnr >= start) & (lnr <= start + 2 * math.log(1.5))
    n = max(5, int(flat.sum()) // 5)
    phase = math.degrees(np.angle(np.mean(np.exp(1j * (np.angle(r[flat][:n]) + 2 * np.pi * f[
        flat][:n] * tau_s)))))
    return {"magnitude": float(np.exp(np.median(lnr[flat]))), "phase_low_deg": phase,
            "median_all": float(np.exp(np.median(lnr))), "sign": 1 if abs(phase) < 90 else -1,
            "plateau_fraction": float(flat.mean()), "bins": int(keep.sum()),
            "plateau_hz": [float(f[flat][0]), float(f[flat][-1])],
            "low_band_hz": [float(f[flat][0]), float(f[flat][:n][-1])],
            "reliable": bool(flat.sum() >= 10 and flat.mean() >= 0.5)}


def _phase_fit(f: NDArray[np.float64], u: NDArray[np.complex128],
               p0: Sequence[float]) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Robust fit of the phase of unit phasors `u` by ``phi0 - 2 pi f tau [- atan(f/fc)]``,
    ``p = (phi0, tau [, ln fc])``: the parameters, their covariance and the residual rms."""
    def resid(p: NDArray[np.float64]) -> NDArray[np.float64]:
        lag = np.arctan(f / np.exp(p[2])) if len(p) > 2 else 0.0
        return np.angle(u * np.exp(-1j * (p[0] - 2 * np.pi * f * p[1] - lag)))
    fit = optimize.least_squares(resid, np.asarray(p0, float), loss="soft_l1", f_scale=0.3)
    s2 = float(np.sum(fit.fun ** 2)) / max(f.size - len(p0), 1)
    return fit.x, np.linalg.pinv(fit.jac.T @ fit.jac) * s2, math.sqrt(s2)


def delay(e: Element, keep: NDArray[np.bool_], model: list[dict],
          modes: list[dict]) -> dict | None:
    """The delay in the phase of measured/model, fitted over the clean bins above the
    element's last modelled peak and last measured peak with a model counterpart (between
    the two the phases differ by a half turn); None with fewer than 20 bins there.

    ``smooth`` is False when the phase scatters by more than 20 degrees about the fit (it
    reads no delay). A first-order low-pass is split from the delay only when the band
    resolves the phase's curvature (corner within twice the band, its log known within
    0.3, correlation with the delay under 0.95) and the magnitude falls by half what that
    low-pass would make it fall at least; otherwise the delay is their sum.
    """
    tops = [m["f"] for m in model if e.name in m["elements"]] + [
        m["f"] for m in modes if m.get("model") and e.name in m["elements"]]
    band = keep & (e.f > 1.1 * max(tops, default=0.0))
    if band.sum() < 20:
        return None
    f, r = e.f[band], e.h[band] / e.model[band]
    u = r / np.abs(r)
    taus = np.linspace(-0.2, 0.2, 4001)
    tau0 = taus[int(np.argmax(np.abs(np.exp(2j * np.pi * np.outer(taus, f)) @ u)))]
    p, cov, rms = _phase_fit(f, u, [np.angle(np.sum(u * np.exp(2j * np.pi * f * tau0))), tau0])
    out = {"tau_ms": 1e3 * p[1], "sigma_ms": 1e3 * math.sqrt(max(cov[1, 1], 0.0)),
           "phase0_deg": math.degrees(p[0]), "rms_deg": math.degrees(rms), "bins": int(f.size),
           "band_hz": [float(f[0]), float(f[-1])], "smooth": bool(rms < math.radians(20)),
           "lowpass": None}
    lp, cov, _ = _phase_fit(f, u, [p[0], 0.5 * p[1], math.log(3 * f[-1])])
    fc, q = math.exp(lp[2]), max(f.size // 5, 3)
    drop = float(np.median(np.log(np.abs(r[:q]))) - np.median(np.log(np.abs(r[-q:]))))
    want = 0.5 * math.log((1 + (f[-q:].mean() / fc) ** 2) / (1 + (f[:q].mean() / fc) ** 2))
    rho = cov[1, 2] / math.sqrt(max(cov[1, 1] * cov[2, 2], 1e-300))
    if fc < 2 * f[-1] and cov[2, 2] < 0.09 and abs(rho) < 0.95 and drop >= 0.5 * want:
        out["lowpass"] = {"fc_hz": fc, "tau_ms": 1e3 * lp[1], "sigma_fc_hz": fc * math.sqrt(
            cov[2, 2]), "magnitude_drop_ln": drop, "lowpass_drop_ln": want}
    else:
        out["lowpass_note"] = (f"no low-pass split from the delay over {f[0]:.2f}-{f[-1]:.2f} "
                               f"Hz (corner {fc:.3g} Hz, magnitude drop {drop:.2f} of "
                               f"{want:.2f} in ln): {out['tau_ms']:.1f} ms is their sum")
    return out


def coupling(e: Element, main: Element | None) -> dict:
    """An unmodelled coherent element: its level (median ``|H|`` ratio over the bins both
    are coherent in, counts/counts) against the drive's collocated readback, and its peaks."""
    both = e.info["mask"] & (main.info["mask"] if main is not None else False)
    return {"level_vs_main": float(np.median(np.abs(e.h[both] / main.h[both])))
            if main is not None and both.sum() >= 5 else None, "bins": int(both.sum()),
            "main": main.name if main is not None else None,
            "peaks_hz": [p["f"] for p in e.info.get("peaks", [])]}


# --- one file, and the repeats ---------------------------------------------------------------

def analyse(path: Path, model: Model | None = None) -> tuple[dict, list[Element]]:
    """The reference reading of one diaggui file against `model` (KAGRA's, by default).

    Returns
    -------
    dict
        What :func:`write` saves as JSON: per element its coherent bands (``[f_low, f_high,
        bins]``), peaks, and scale and delay or coupling; the measured modes and their
        model counterparts; the model's visible modes and its pole pairs in the band.
    list of Element
        The elements, for the figure.
    """
    optic, drive, elements, averages = read_elements(path)
    model = model if model is not None else load_model(optic)
    fine = attach_model(model, drive, elements)
    df = float(elements[0].f[1] - elements[0].f[0])
    for e in elements:
        e.info["mask"] = mask = coherent_mask(e.coh)
        e.info["coherent"] = any(b - a >= COHERENT_RUN for a, b in runs(mask))
        e.info["peaks"] = element_peaks(e, mask, averages) if e.info["coherent"] else []
    coherent = [e for e in elements if e.info["coherent"]]
    modes = group_modes({e.name: e.info["peaks"] for e in coherent}, df)
    mmodes = model_modes(model, drive, coherent, fine)
    lam = model.poles[(model.poles.imag > 1e-9) & (model.poles.imag < 2 * np.pi * fine[-1])]
    poles = [{"f": float(abs(v) / (2 * np.pi)), "Q": float(abs(v) / (-2 * v.real)),
              "label": label(model, v)} for v in sorted(lam, key=abs)]
    correspond(modes, mmodes, elements, poles)
    main = next((e for e in coherent if e.name == MAIN.get(drive)), None)
    report: dict = {"file": path.name, "optic": optic, "drive": drive, "averages": averages,
                    "bin_hz": df, "elements": {}, "modes": modes, "model_modes": mmodes,
                    "model_poles": poles}
    for e in elements:
        item = {"modelled": e.modelled, "model_ratios": list(e.ratios),
                "coherent": e.info["coherent"], "peaks": e.info["peaks"],
                "bands": [[float(e.f[a]), float(e.f[b - 1]), b - a] for a, b in runs(
                    e.info["mask"])]}
        if e.info["coherent"] and e.modelled:
            keep = clean_bins(e, averages)
            item["scale"] = sc = scale(e, keep)
            item["delay"] = d = delay(e, keep, mmodes, modes) if sc and sc["reliable"] else None
            if d and d["smooth"]:
                item["scale"] = scale(e, keep, d["tau_ms"] / 1e3)
            e.info["scale"] = item["scale"]
        elif e.info["coherent"]:
            item["coupling"] = coupling(e, main)
        report["elements"][e.name] = item
    return report, elements


def repeats(first: dict, second: dict) -> list[dict]:
    """The modes two repeats of one test share: their frequencies and the difference in
    units of its sigma, a check of the sigmas."""
    out = []
    for m in first["modes"]:
        near = [n for n in second["modes"] if abs(n["f"] - m["f"]) <= max(
            3 * first["bin_hz"], 5 * math.hypot(m["sigma_f"], n["sigma_f"]))]
        if near:
            n = min(near, key=lambda x: abs(x["f"] - m["f"]))
            out.append({"f_a": m["f"], "sigma_a": m["sigma_f"], "f_b": n["f"],
                        "sigma_b": n["sigma_f"], "sigmas": (n["f"] - m["f"]) / math.hypot(
                            m["sigma_f"], n["sigma_f"])})
    return out


# --- the figure, the files and the table -----------------------------------------------------

def figure(report: dict, elements: list[Element], path: Path) -> None:
    """Each coherent element's magnitude and phase: the measurement (counts/count; coherent
    bins black, the others grey), the model at the measurement's resolution times the
    element's scale (dashed where unreliable), the fitted peaks (red) and the model's
    visible peaks (blue), each listed in its panel."""
    shown = [e for e in elements if e.info["coherent"]]
    nrow = max(1, math.ceil(len(shown) / 3))
    fig = Figure(figsize=(18.6, 5.4 * nrow), layout="constrained")
    grid = fig.add_gridspec(2 * nrow, 3, height_ratios=[2.2, 1] * nrow)
    fig.suptitle(f"{report['file']}: {report['optic']} driven at {report['drive']}, "
                 f"{report['averages']} averages, {report['bin_hz']:.4f} Hz bins")
    for k, e in enumerate(shown):
        mag = fig.add_subplot(grid[2 * (k // 3), k % 3])
        _panel(mag, fig.add_subplot(grid[2 * (k // 3) + 1, k % 3], sharex=mag), e, report)
    fig.savefig(path, dpi=80)


def _panel(mag: object, ph: object, e: Element, report: dict) -> None:
    """One element's magnitude (`mag`) and phase (`ph`) axes."""
    m, sc = e.info["mask"], e.info.get("scale")
    for sel, style in ((~m, {"color": "0.75", "ms": 1.5}), (m, {"color": "k", "ms": 2.5})):
        mag.loglog(e.f[sel], np.abs(e.h[sel]), ".", **style)
        ph.semilogx(e.f[sel], np.angle(e.h[sel], deg=True), ".", **style)
    if sc:
        model = e.info["fine"] * sc["magnitude"] * np.exp(1j * math.radians(sc["phase_low_deg"]))
        mag.loglog(e.info["grid"], np.abs(model), "-" if sc["reliable"] else "--", lw=1,
                   color="tab:blue", label=f"model x {sc['magnitude']:.3g} at "
                   f"{sc['phase_low_deg']:.0f} deg" + ("" if sc["reliable"] else
                                                       " (ratio not flat: unreliable)"))
        ph.semilogx(e.info["grid"], np.angle(model, deg=True), "-", color="tab:blue", lw=0.8)
        shown = [mm for mm in report["model_modes"] if e.name in mm["elements"]]
        fp = np.array([mm["elements"][e.name]["f_peak"] for mm in shown])
        mag.plot(fp, np.interp(fp, e.info["grid"], np.abs(model)), "v", color="tab:blue", ms=6)
        mag.text(0.99, 0.87, "model peaks (Hz): " + " ".join(f"{mm['f']:.3f}" for mm in shown),
                 transform=mag.transAxes, ha="right", va="top", fontsize=8, color="tab:blue",
                 bbox={"fc": "white", "ec": "none", "alpha": 0.8, "pad": 1})
        mag.legend(loc="lower left", fontsize=8)
    for p in e.info["peaks"]:
        mag.axvline(p["f"], color="tab:red", lw=0.8, ls="--")
    if e.info["peaks"]:
        mag.text(0.99, 0.98, "fitted peaks (Hz): " + " ".join(f"{p['f']:.3f}" for p in e.info[
            "peaks"]), transform=mag.transAxes, ha="right", va="top", fontsize=8,
                 color="tab:red", bbox={"fc": "white", "ec": "none", "alpha": 0.8, "pad": 1})
    mag.set_title(e.name + ("" if sc else " (not modelled: a coupling)" if not e.modelled
                            else " (no clean bins)"), fontsize=10)
    seen = np.abs(e.h[m])
    mag.set(ylabel="|H| (counts/count)", xlim=(e.f[0], e.f[-1]),
            ylim=(seen.min() / 10, seen.max() * 30))
    ph.set(ylabel="phase (deg)", xlabel="frequency (Hz)", ylim=(-185, 185),
           yticks=[-180, -90, 0, 90, 180])
    for a in (mag, ph):
        a.grid(True, which="both", lw=0.3)


def write(report: dict, elements: list[Element], out: Path) -> None:
    """``out/<file>.json`` and ``out/<file>.png``."""
    out.mkdir(parents=True, exist_ok=True)
    stem = Path(report["file"]).stem
    (out / f"{stem}.json").write_text(json.dumps(report, indent=1, default=lambda x: x.item())
                                      + "\n")
    figure(report, elements, out / f"{stem}.png")


def table(report: dict) -> list[str]:
    """The lines printed for one file: its modes, its elements' scales, delays and
    couplings, and its repeat's check."""
    lines = [f"{report['file']}  {report['optic']} {report['drive']}  ({report['averages']} "
             f"averages, {report['bin_hz']:.4f} Hz bins)", f"  {'f (Hz)':>8} {'sigma':>7} "
             f"{'Q':>9}  {'model':>7} {'shift':>7}  {'label':6} seen in"]
    for m in report["modes"]:
        q = f"{m['Q']:.0f}" if m["resolved"] else f">{m['Q_min']:.0f}"
        mm, own = m["model"] or {}, m.get("own_dof_model") or {}
        seen = ",".join(map(short, m["elements"]))
        lines.append(f"  {m['f']:8.4f} {m['sigma_f']:7.4f} {q:>9}  " + (
            f"{mm['f']:7.3f} {mm['shift_pct']:+6.1f}%  {mm['label']:6}" if mm else
            f"{'none':>7} {'':7}  {own.get('label', ''):6}") + f" {seen}" + (
            f"  (coupling; own DOF's {own['f']:.3f} Hz)" if own else ""))
    lines.append(f"  {'element':9} {'scale':>10} {'phase':>6} {'ok':>3} {'delay ms':>14} "
                 f"{'band Hz':>12}  level vs main; peaks")
    for name, it in report["elements"].items():
        sc, d, c = it.get("scale"), it.get("delay"), it.get("coupling")
        row = f"  {short(name):9} " + (f"{sc['magnitude']:10.3g} {sc['phase_low_deg']:6.0f} "
                                       f"{'yes' if sc['reliable'] else 'no':>3} " if sc else
                                       " " * 22)
        row += (f"{d['tau_ms']:7.1f}+-{d['sigma_ms']:<5.1f}{'' if d['smooth'] else '?'}"
                f"{d['band_hz'][0]:6.2f}-{d['band_hz'][1]:<5.1f}" if d else " " * 27)
        if c:
            row += f"  x{c['level_vs_main'] or float('nan'):.3g} of {short(c['main'] or 'X_')};"
        lp = (d or {}).get("lowpass")
        row += (f"  low-pass {lp['fc_hz']:.1f} Hz + {lp['tau_ms']:.1f} ms;" if lp else "")
        if it["coherent"]:
            lines.append(row + " " + " ".join(f"{p['f']:.3f}" for p in it["peaks"]))
    lines += [f"  repeat of {report['repeat']['of']}: {r['f_a']:.4f} vs {r['f_b']:.4f} Hz, "
              f"{r['sigmas']:+.1f} sigma" for r in report.get("repeat", {}).get("modes", [])]
    return lines


def main(argv: Sequence[str]) -> int:
    """``python -m twind.lab.kagra_reference -o DIR [FILES...]``: the reference of each file
    (default: the five of ``tests/data/kagra/``) written to DIR, its table printed."""
    args = list(argv)
    if "-o" not in args[:-1]:
        print("usage: python -m twind.lab.kagra_reference -o DIR [FILES...]", file=sys.stderr)
        return 2
    at = args.index("-o")
    out, names = Path(args[at + 1]), args[:at] + args[at + 2:] or list(FILES)
    done = {}
    for path in (Path(n) if Path(n).exists() else DATA / n for n in names):
        done[path.name] = analyse(path)
    for name, (report, _) in done.items():
        twin = name[:-5] + "a.xml" if name.endswith("b.xml") else ""
        if twin in done:
            report["repeat"] = {"of": twin, "modes": repeats(done[twin][0], report)}
    for report, elements in done.values():
        write(report, elements, out)
        print("\n".join(table(report)) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
