"""Discrete-time pieces shared by the engine and its checks.

The plant is discretised with the bilinear (trapezoidal) rule, its poles matched
(:func:`bilinear`). docs/model.md's loop has exactly one cycle of delay, ``exp(-s T)``, and
nothing for the DAC's hold; a zero-order-hold plant would add half a cycle (1.9e-3 rad at 10
Hz), enough to pass for a ``loop_delay`` effect in a diagnosis. The bilinear plant behind a
whole-cycle delay reproduces the model to ~(wT)^2/12.
Filter sections are transposed direct form II, as in the kernel.
"""

from __future__ import annotations

from functools import lru_cache

import control
import numpy as np
import scipy.linalg
from numpy.typing import NDArray
from scipy import signal

from twind import DOFS
from twind.loop.damping import DampingLoop
from twind.loop.filtermodule import IDENTITY_SECTION

SS = tuple  # (A, B, C, D) of a discrete state space, numpy arrays


def bilinear(A: NDArray, B: NDArray, C: NDArray, dt: float) -> SS:
    """Bilinear discretisation of ``x' = A x + B u, y = C x`` with its poles matched; returns
    ``(Ad, Bd, Cd, Dd)``.

    Each mode's continuous eigenvalue ``lambda`` is first moved to ``(2 / dt) tanh(lambda dt
    / 2)``, whose bilinear image is ``exp(lambda dt)``: every mode keeps its frequency and Q
    however high it lies (unmatched, a violin mode at 2.35 kHz would land 6 % low at 16384
    Hz), while a pendulum mode moves by ``(lambda dt)^2 / 12``, 1e-8.

    Parameters
    ----------
    A, B, C : ndarray
        Continuous state, input and output matrices.
    dt : float
        Model cycle (s).

    Returns
    -------
    Ad, Bd, Cd, Dd : ndarray
        The discrete matrices; ``Dd`` is the feedthrough the trapezoidal rule adds.
    """
    Ad, Bd, Cd, Dd, _ = signal.cont2discrete((_matched(A, dt), B, C,
                                              np.zeros((C.shape[0], B.shape[1]))),
                                             dt, method="bilinear")
    return Ad, Bd, Cd, Dd


MATCH_CONDITION = 1e10
"""Beyond this eigenvector condition number the poles are left as the bilinear rule puts
them: a basis that ill-conditioned would cost more digits than the match gains."""


def _matched(A: NDArray, dt: float) -> NDArray:
    """`A` with each eigenvalue ``lambda`` moved to ``(2 / dt) tanh(lambda dt / 2)``."""
    if not A.size:
        return A
    lam, V = np.linalg.eig(A)
    if np.linalg.cond(V) > MATCH_CONDITION:
        return A
    warped = (2 / dt) * np.tanh(lam * dt / 2)
    return (V @ np.diag(warped) @ np.linalg.inv(V)).real


def delay_samples(delay_s: float, rate_hz: float) -> int:
    """The loop delay as a whole number of model cycles.

    Parameters
    ----------
    delay_s : float
        The loop delay (s).
    rate_hz : float
        Model rate.

    Returns
    -------
    int

    Raises
    ------
    ValueError
        If the delay is not a whole number (at least one) of cycles.
    """
    n = delay_s * rate_hz
    if abs(n - round(n)) > 1e-6 or round(n) < 1:
        msg = f"loop delay {delay_s} s is not a whole number (>= 1) of cycles at {rate_hz} Hz"
        raise ValueError(msg)
    return int(round(n))


def balance(sos: NDArray[np.float64], rate_hz: float) -> NDArray[np.float64]:
    """The same cascade with its gain spread evenly over the sections.

    A cascade whose first section carries the whole gain (1e-23 for an all-pole roll-off)
    passes signals through a huge dynamic range; spreading it keeps each section's peak gain
    equal, which the state-space checks and the round-off of long runs both need.

    Parameters
    ----------
    sos : ndarray, shape (n, 6)
        Sections with ``a0 = 1``.
    rate_hz : float
        Model rate, for the sections' peak gains.

    Returns
    -------
    ndarray, shape (n, 6)
        The same response, each section's numerator scaled.
    """
    if len(sos) == 0:
        return sos
    shares = _balanced_shares(np.ascontiguousarray(sos, dtype=float).tobytes(), len(sos), rate_hz)
    if shares is None:
        return sos
    out = sos.copy()
    out[:, :3] *= shares[:, None]
    return out


@lru_cache(maxsize=1024)
def _balanced_shares(coefficients: bytes, n: int, rate_hz: float) -> NDArray[np.float64] | None:
    """Each section's numerator factor for :func:`balance` (None: leave the cascade as it
    is); cached by the coefficients, as every stability check of a live change meets the
    same stages again."""
    sos = np.frombuffer(coefficients).reshape(n, 6)
    f = np.geomspace(1e-3, 0.45 * rate_hz, 512)
    peaks = np.array([np.abs(signal.sosfreqz(sec[None], worN=f, fs=rate_hz)[1]).max() for sec in sos])
    if not np.all(np.isfinite(peaks)) or np.any(peaks == 0):
        return None
    shares = np.exp(np.mean(np.log(peaks))) / peaks
    shares.flags.writeable = False
    return shares


def stage_sections(loop: DampingLoop, dof: str, rate_hz: float) -> tuple[NDArray, dict[int, slice]]:
    """Every defined stage's balanced sections for `dof`, and the rows of each FM.

    Parameters
    ----------
    loop : DampingLoop
        The optic's loop.
    dof : str
        POS, PIT, YAW or SIDE.
    rate_hz : float
        Model rate.

    Returns
    -------
    sos : ndarray, shape (n, 6)
        Every stage's sections, on or off, with ``a0 = 1``.
    where : dict of int to slice
        The rows of each FM in `sos`.
    """
    sos, where = loop.modules[dof].section_layout(rate_hz)
    sos = sos / sos[:, 3:4]  # the kernel takes a0 = 1
    for rows in where.values():
        sos[rows] = balance(sos[rows], rate_hz)
    return sos, where


def module_sections(loop: DampingLoop, dof: str, rate_hz: float) -> NDArray[np.float64]:
    """Sections the engine runs for `dof`: switched-off stages as identity sections.

    Parameters
    ----------
    loop : DampingLoop
        The optic's loop.
    dof : str
        POS, PIT, YAW or SIDE.
    rate_hz : float
        Model rate.

    Returns
    -------
    ndarray, shape (n, 6)
    """
    sos, where = stage_sections(loop, dof, rate_hz)
    for fm, rows in where.items():
        if fm not in loop.modules[dof].on:
            sos[rows] = IDENTITY_SECTION
    return sos


def modal(Ad: NDArray, B: NDArray, C: NDArray) -> tuple[NDArray, ...]:
    """Real modal form of a discrete plant: each state couples only to its mode partner.

    Returns
    -------
    a_diag, a_off : ndarray, shape (n,)
        ``x+[i] = a_diag[i] x[i] + a_off[i] x[partner[i]] + ...``
    partner : ndarray of int, shape (n,)
    B_modal, C_modal : ndarray
        Input and output matrices in the modal coordinates (the feedthrough is unchanged).
    to_modal : ndarray, shape (n, n)
        ``x = to_modal @ z``: the physical state of modal state ``z``.

    Parameters
    ----------
    Ad, B, C : ndarray
        Discrete state, input and output matrices.

    Raises
    ------
    ValueError
        If the modes are nearly degenerate (no well-conditioned modal basis).
    """
    # LAPACK returns each complex pair together, positive imaginary part first, as cdf2rdf wants
    w, v = np.linalg.eig(Ad)
    wr, vr = scipy.linalg.cdf2rdf(w, v)
    cond = np.linalg.cond(vr)
    if cond > 1e10:
        msg = f"the plant's modes are nearly degenerate (eigenvector condition {cond:.2g})"
        raise ValueError(msg)
    n = len(w)
    partner = np.arange(n)
    a_off = np.zeros(n)
    i = 0
    while i < n:
        if abs(w[i].imag) > 0:
            partner[i], partner[i + 1] = i + 1, i
            a_off[i], a_off[i + 1] = wr[i, i + 1], wr[i + 1, i]
            i += 2
        else:
            i += 1
    inv = np.linalg.inv(vr)
    return np.diag(wr).copy(), a_off, partner, inv @ B, C @ vr, vr


def _series(first: SS, second: SS) -> SS:
    """``second`` after ``first``."""
    A1, B1, C1, D1 = first
    A2, B2, C2, D2 = second
    A = np.block([[A1, np.zeros((A1.shape[0], A2.shape[0]))], [B2 @ C1, A2]])
    return A, np.vstack([B1, B2 @ D1]), np.hstack([D2 @ C1, C2]), D2 @ D1


def _parallel(systems: list[SS]) -> SS:
    """Independent systems side by side (block diagonal)."""
    return tuple(scipy.linalg.block_diag(*(s[i] for s in systems)) for i in range(4))


def _sections(sos: NDArray, gain: float) -> SS:
    # each transposed-DF2 section: y = b0 v + z0; z0+ = (b1 - a1 b0) v - a1 z0 + z1; ...
    sys: SS = (np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), np.array([[gain]]))
    for b0, b1, b2, _, a1, a2 in sos:
        sec = (np.array([[-a1, 1.0], [-a2, 0.0]]), np.array([[b1 - a1 * b0], [b2 - a2 * b0]]),
               np.array([[1.0, 0.0]]), np.array([[b0]]))
        sys = _series(sys, sec)
    return sys


def closed_loop_matrices(loop: DampingLoop, rate_hz: float) -> SS:
    """The engine's closed loop (noise off) as discrete ``(A, B, C, D)``.

    Inputs are the four EXC test points; outputs IN1, IN2 and OUT of POS, PIT, YAW, SIDE
    (12 rows). It shares the engine's discretisation (:func:`bilinear`, the sections) but not
    its kernel, so python-control's ``forced_response`` on it checks the kernel; the golden
    and Welch tests check the discretisation.

    Parameters
    ----------
    loop : DampingLoop
        The optic's loop.
    rate_hz : float
        Model rate.

    Returns
    -------
    A, B, C, D : ndarray
    """
    A, Bc, _, C = loop.plant.osem_state_space()
    Ad, Bd, Cd, Dd = bilinear(A, Bc @ loop.plant.output_matrix, C, 1.0 / rate_hz)
    inmat = loop.plant.input_matrix
    plant: SS = (Ad, Bd, inmat @ Cd, inmat @ Dd)
    nd = delay_samples(loop.plant.delay_s, rate_hz)
    one = (np.eye(nd, k=-1), np.eye(nd, 1), np.eye(1, nd, nd - 1), np.zeros((1, 1)))
    plant = _series(_parallel([one] * 4), plant)
    Ag, Bg, Cg, _ = plant
    Ak, Bk, Ck, Dk = _parallel([_sections(module_sections(loop, d, rate_hz), loop.modules[d].gain)
                                for d in DOFS])
    nk = Ak.shape[0]
    Acl = np.block([[Ag + Bg @ Dk @ Cg, Bg @ Ck], [Bk @ Cg, Ak]])
    Bcl = np.vstack([Bg @ Dk, Bk])
    Ccl = np.vstack([np.hstack([Cg, np.zeros((4, nk))]),
                     np.hstack([Cg, np.zeros((4, nk))]),
                     np.hstack([Dk @ Cg, Ck])])
    Dcl = np.vstack([np.zeros((4, 4)), np.eye(4), Dk])
    return Acl, Bcl, Ccl, Dcl


def closed_loop_modes(loop: DampingLoop, rate_hz: float, below_hz: float = 2.0
                      ) -> list[tuple[float, float]]:
    """The damped suspension modes of the engine's discrete closed loop: frequency (Hz) and
    Q of each pole pair below `below_hz` (the filters' own poles lie above), lowest first.

    Parameters
    ----------
    loop : DampingLoop
        The optic's loop.
    rate_hz : float
        Model rate.
    below_hz : float
        Highest mode frequency kept.

    Returns
    -------
    list of (float, float)
    """
    z = np.linalg.eigvals(closed_loop_matrices(loop, rate_hz)[0])
    s = np.log(z[(np.abs(z) > 0) & (z.imag > 0)]) * rate_hz  # delay states sit at z = 0
    s = s[np.abs(s) < 2 * np.pi * below_hz]
    return sorted((float(abs(p) / (2 * np.pi)), float(abs(p) / (-2 * p.real))) for p in s)


def discrete_closed_loop(loop: DampingLoop, rate_hz: float):  # noqa: ANN201 - control.StateSpace
    """:func:`closed_loop_matrices` as a python-control discrete ``StateSpace``.

    Parameters
    ----------
    loop : DampingLoop
        The optic's loop.
    rate_hz : float
        Model rate.

    Returns
    -------
    control.StateSpace
    """

    return control.ss(*closed_loop_matrices(loop, rate_hz), 1.0 / rate_hz)
