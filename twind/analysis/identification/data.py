"""The measured bins a fit uses: ``IN1/EXC`` of the excited DOFs with their errors, chosen
by coherence."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from twind.analysis.estimation.tfset import Kernel, TFSet
from twind.analysis.identification.params import FitError


MIN_COHERENCE = 0.5
"""Below this the Bendat-Piersol error (and the estimate's bias) is no longer trustworthy."""


SURE_COHERENCE = 0.95
"""A bin at least this coherent is used whatever its neighbours (a multisine's tone)."""


SMOOTH_BINS = 11
"""Bins chosen by the coherence averaged over this many neighbours."""


# ------------------------------------------------------------------------------ data and model
@dataclass(frozen=True)
class FitData:
    """Measured ``IN1/EXC`` bins a fit uses, with their errors.

    Attributes
    ----------
    frequency_hz : ndarray, shape (nf,)
    responses, excited : list of str
        The DOFs (POS, PIT, YAW, SIDE) whose IN1 was read and those excited.
    H, sigma : ndarray, shape (nf, nr, ne)
        Measured ``IN1/EXC`` and the standard error of its real and imaginary parts.
    mask : ndarray of bool, shape (nf, nr, ne)
        Bins used: coherent enough, finite, inside the band.
    averages : int
    resolution_hz : float
        Bin width of a Hann-windowed estimate (0 for a rectangular window).
    kernel : Kernel, optional
        What each estimate sees of the true response, when not the response at its bin (LPM).
    correlation : ndarray of complex, shape (nf, nr, nr, ne), optional
        Correlation of the errors of one bin's responses to one excitation (LPM); the
        residuals are whitened with it, otherwise bin by bin.
    """

    frequency_hz: NDArray[np.float64]
    responses: list[str]
    excited: list[str]
    H: NDArray[np.complex128]
    sigma: NDArray[np.float64]
    mask: NDArray[np.bool_]
    averages: int
    resolution_hz: float = 0.0
    kernel: Kernel | None = None
    correlation: NDArray[np.complex128] | None = None

    @classmethod
    def from_tfset(cls, tfs: TFSet, min_coherence: float = MIN_COHERENCE,
                   band: tuple[float, float] | None = None,
                   whole: Sequence[tuple[float, float]] = ()) -> FitData:
        """The bins of `tfs` worth fitting; a FitError when none is.

        Those whose neighbour-averaged coherence reaches `min_coherence` (or whose own
        reaches :data:`SURE_COHERENCE`); with `min_coherence` <= 0, every response at the
        frequencies where the excited DOF's own response is coherent (``twind diagnose``).
        In the bands `whole` (Hz) every bin is used, coherent or not: chosen by frequency
        alone, their errors are not biased by the choice (where a narrow mode may lie).

        Parameters
        ----------
        tfs : TFSet
            The measurement; its IN1/EXC is fitted.
        min_coherence : float
            The neighbour-averaged coherence a bin must reach; <= 0 for every response
            where the excitation reached the optic.
        band : (float, float), optional
            Only the bins in this band (Hz).
        whole : sequence of (float, float)
            Bands (Hz) used bin by bin, whatever their coherence.

        Returns
        -------
        FitData

        Raises
        ------
        FitError
            If no bin is usable.
        """
        f = tfs.frequency_hz
        H, sigma = tfs.tf["IN1"], tfs.sigma("IN1")
        g2 = tfs.coherence["IN1"]
        # a bin this coherent on its own is no fluke (P < 1e-5 from zero coherence with 5
        # averages): it keeps the tones of a sparse multisine, which smoothing would dilute
        coherent = (smoothed(g2) >= min_coherence) | (g2 >= max(SURE_COHERENCE, min_coherence))
        if min_coherence <= 0:
            # every response where the excitation reached the optic (its own DOF coherent):
            # the incoherent elements there carry the noise's errors, and together they
            # show a coupling too small to lift one bin out of the noise
            own = [tfs.responses.index(d) for d in tfs.excited]
            driven = smoothed(g2[:, own, range(len(own))]) >= MIN_COHERENCE
            coherent = np.broadcast_to(driven[:, None, :], g2.shape)
        for lo, hi in whole:
            coherent = coherent | ((f >= lo) & (f <= hi))[:, None, None]
        mask = coherent & np.isfinite(H) & (sigma > 0)
        mask &= (f > 0)[:, None, None]
        if band is not None:
            mask &= ((f >= band[0]) & (f <= band[1]))[:, None, None]
        if not mask.any():
            msg = (f"no bin of {tfs.optic}'s IN1/EXC reaches coherence "
                   f"{min_coherence if min_coherence > 0 else MIN_COHERENCE:g}"
                   + (f" in {band[0]:g}-{band[1]:g} Hz" if band else ""))
            raise FitError(msg)
        resolution = float(np.median(np.diff(f))) if tfs.window == "hann" and f.size > 1 else 0.0
        return cls(f, list(tfs.responses), list(tfs.excited), H, sigma, mask, tfs.averages,
                   resolution, tfs.kernel, tfs.in1_correlation)

    @property
    def bins(self) -> int:
        """Number of complex bins used."""
        return int(self.mask.sum())

    def span(self) -> FitData:
        """The same bins with the arrays cut to the frequencies from the first used bin to
        the last: a measurement up to Nyquist fitted below 30 Hz is evaluated, whitened and
        its neighbouring bins paired there alone."""
        used = np.flatnonzero(self.mask.any(axis=(1, 2)))
        cut = slice(int(used[0]), int(used[-1]) + 1)
        kernel = (None if self.kernel is None
                  else Kernel(self.kernel.offsets_hz, self.kernel.weights[cut]))
        return replace(self, frequency_hz=self.frequency_hz[cut], H=self.H[cut],
                       sigma=self.sigma[cut], mask=self.mask[cut], kernel=kernel,
                       correlation=None if self.correlation is None else self.correlation[cut])

    def whiten(self, model: NDArray[np.complex128]) -> NDArray[np.float64]:
        """``(H - model) / sigma`` over the used bins, real parts then imaginary parts;
        with a :attr:`correlation`, decorrelated across each bin's used responses."""
        if self.correlation is None:
            r = (self.H[self.mask] - model[self.mask]) / self.sigma[self.mask]
        else:
            r = np.where(self.mask, (self.H - model) / np.where(self.mask, self.sigma, 1), 0)
            r = np.einsum("feij,fje->fie", self._whitener, r)[self.mask]
        return np.concatenate([r.real, r.imag])

    def whitened_change(self, dT: NDArray[np.complex128], at: NDArray[np.int64]
                        ) -> NDArray[np.complex128]:
        """What a model change `dT` at bins `at` (sorted; shape (..., len(at), nr, ne))
        takes off :meth:`whiten`'s residuals there, as complex numbers: one per used entry,
        in the order whose real parts, then imaginary parts, :meth:`whiten` lists.

        Parameters
        ----------
        dT : ndarray of complex, shape (..., len(at), nr, ne)
            The change of the modelled IN1/EXC at those bins.
        at : ndarray of int
            Frequency indices of the bins, sorted.

        Returns
        -------
        ndarray of complex, shape (..., used)
            One per used entry of those bins.
        """
        used = self.mask[at]
        if self.correlation is None:
            return dT[..., used] / self.sigma[at][used]
        r = np.where(used, dT / np.where(used, self.sigma[at], 1), 0)
        return np.einsum("feij,...fje->...fie", self._whitener[at], r)[..., used]

    @functools.cached_property
    def _whitener(self) -> NDArray[np.complex128]:
        """``L^-1`` per bin and excitation, (nf, ne, nr, nr), with ``L L^H`` the correlation
        of the used responses (zero rows and columns for the unused)."""
        nf, nr, ne = self.H.shape
        out = np.zeros((nf, ne, nr, nr), dtype=complex)
        used = np.moveaxis(self.mask, 2, 1)  # (nf, ne, nr)
        rho = np.moveaxis(self.correlation, 3, 1)  # (nf, ne, nr, nr)
        for pattern in {tuple(u) for u in used.reshape(-1, nr) if u.any()}:
            at = np.all(used == np.array(pattern), axis=2)
            rows = np.flatnonzero(pattern)
            c = rho[at][:, rows][:, :, rows]
            # eigenvalues floored, so that responses correlated to rounding (or a correlation
            # from elsewhere that lost definiteness) still whiten to finite residuals
            w, v = np.linalg.eigh(c)
            c = (v * np.clip(w, 1e-3, None)[:, None, :]) @ np.conj(np.swapaxes(v, 1, 2))
            block = np.linalg.inv(np.linalg.cholesky(c))
            sub = out[at]
            sub[:, rows[:, None], rows[None, :]] = block
            out[at] = sub
        return out


def smoothed(coherence: NDArray[np.float64], bins: int = SMOOTH_BINS) -> NDArray[np.float64]:
    """Running mean over `bins` neighbouring frequencies.

    Bins are chosen by this, not by their own coherence: with few averages the estimate
    scatters upward, and choosing the bins that happen to look coherent picks exactly those
    whose error the coherence understates.
    """
    return ndimage.uniform_filter1d(coherence, bins, axis=0, mode="nearest")
