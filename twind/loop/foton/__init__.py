"""Foton filter *design strings*: parse them into continuous zpk, discretize them for the CDS.

A foton design string is what a commissioner types into foton (and what a filter file keeps
on its ``# DESIGN`` lines), e.g. ``zpk([0],[30],6.283185307179586,"n")`` or
``zpk([1],[10],1,"n")gain(3)``.  Factors written one after the other (optionally joined by
``*``) multiply.  Whitespace, newlines, backslash line continuations and ``%`` comments
(which IIRrational writes inside ``zpk`` vectors) are ignored.

Conventions
-----------
As LIGO's own foton reads them (``python-foton`` 4.1.5, the CDS DTT project's bindings,
``foton.FilterDesign(design, rate)``), measured function by function and held against it
by ``tests/test_foton_ligo.py`` over generated designs.  Each function is its own filter;
they multiply.  ``plane`` is ``"s"`` (rad/s, as written; the default), ``"f"`` (Hz, same
sign: ``s = 2 pi r``) or ``"n"`` (Hz, stable roots written positive: ``s = -2 pi r``, each
root divided by its magnitude, ``s/(2 pi)`` at the origin, so ``gain`` is the DC gain).

* ``zpk(zeros, poles, gain[, plane])``; complex roots ``a+i*b;a-i*b`` (also ``a+b*i``,
  ``bi``, ``i*-b``) in conjugate pairs; ``;`` or ``,`` between elements.
* ``pole(f[, gain[, plane]])`` = ``gain/(s + w)``, ``zero`` its inverse;
  ``pole2(f, Q[, gain[, plane]])`` = ``gain/(s^2 + (w/|Q|) s + w^2)`` (a double real pole
  at ``-w`` for ``|Q| <= 1/2``), ``zero2`` its inverse; ``w`` is ``f`` in "s", ``2 pi f``
  otherwise, "n" normalises.
* ``rpoly(num, den, gain)``: ``gain num(s)/den(s)``, coefficients highest power first.
* ``gain(g[, "scalar"|"dB"])``.
* ``notch(f, Q[, depth])``: zeros and poles at ``f``; foton's ``Q`` is ``f`` over *half*
  the width between the -3 dB points, so the poles' quality is ``sqrt(1 - 2 r^2) Q (4Q^2 -
  1)/(8Q^2 - 1)``, ``r`` the depth as a ratio (0 for depth 0, an infinitely deep notch;
  otherwise deeper than 3.01 dB), and the zeros' damping ``r`` times the poles'.
  ``resgain(f, Q[, height])`` is the inverse of the notch of depth ``height`` (30 dB by
  default).  Both need complex roots (quality above 1/2).
* ``comb(f, Q[, amplitude[, N]])``: a resgain (amplitude > 0) or notch (< 0; 0: infinitely
  deep) at ``f`` and its harmonics up to the N-th, all below Nyquist for N = 0.
* ``butter(type, order, f1[, f2])``, ``cheby1(type, order, ripple, f1[, f2])``,
  ``cheby2(type, order, attenuation, f1[, f2])``, ``ellip(type, order, ripple,
  attenuation, f1[, f2])``, type ``"LowPass"``, ``"HighPass"``, ``"BandPass"`` or
  ``"BandStop"`` (any case), band edges in either order: digital designs, the analog
  prototype at the prewarped edges then the bilinear transform (``scipy.signal`` with
  ``fs``).
* z-plane designs: ``sos(gain, [b1;b2;a1;a2;...][, "s"|"o"])`` (sections ``(1 + b1/z +
  b2/z^2)/(1 + a1/z + a2/z^2)``; "o" orders each a1, a2, b1, b2), ``biquad(b0, b1, b2, a1,
  a2)``, ``direct([b0;b1;...], [a1;a2;...])`` (denominator ``1 - a1/z - ...``) and
  ``zroots(zeros, poles[, gain])`` (``gain prod(z - zeros)/prod(z - poles)``); a numerator
  shorter than the denominator counts its missing zeros at z = -1.
* A function with more zeros than poles gets foton's poles at twice the sample rate: a
  Butterworth pair for two missing, ``-2fs/(s + 2fs)`` for one, which turns the sign of the
  response (``zero(5)`` has DC gain -5).
* Poles in the right half plane (or outside the unit circle, or at or above Nyquist) are
  refused, as foton refuses them.

Discretization
--------------
Every s-plane root is prewarped radially, ``|r| -> 2 fs tan(|r| / 2 fs)`` (a root above
Nyquist folds through infinity), then ``s -> 2 fs (z-1)/(z+1)``, each factor normalised at
DC; missing zeros go to z = -1.  The digital designs (IIR, z-plane, foton's extra poles)
depend on the sample rate: :func:`parse_design` with ``rate_hz`` returns the continuous
filter whose discretization is exactly foton's (roots unwarped, the inverse of the
prewarp), which is what the model's continuous responses use.

What the bilinear transform cannot keep is the high-frequency asymptote: each pole in excess
of the zeros makes the discrete response differ by ``tan(x)/x - 1 ~ x^2/3``, ``x = pi f/fs``
(1.2e-4 at 100 Hz for 16384 Hz); the nominal FM2 (8 poles) is therefore 1e-3 off at 100 Hz,
as any bilinear CDS implementation of it is.
"""

from __future__ import annotations

from twind.loop.foton.parser import n_plane_design, parse_design
from twind.loop.foton.sections import design_to_sos, implementation, zpk_to_sos
from twind.loop.foton.zpk import ZPK

__all__ = [
    "NOMINAL_FM1",
    "NOMINAL_FM2",
    "NOMINAL_FM3",
    "ZPK",
    "design_to_sos",
    "implementation",
    "n_plane_design",
    "parse_design",
    "zpk_to_sos",
]

# --- nominal damping controller (sos_etmx_nominal.json "controller"), foton "n" plane ------
# FM1: an "n"-plane zero at the origin is s/(2 pi) (unity at 1 Hz); the gain 2 pi makes it s.
NOMINAL_FM1 = 'zpk([0],[30.000330908653446],6.283185307179586,"n")'
# FM2 "Cheby": pole pairs (f, Q) written f/(2Q) +- i*f*sqrt(1 - 1/(4Q^2)) in Hz, DC gain 1.
NOMINAL_FM2 = (
    "zpk([],"
    "[2.784757795351504+i*3.1942103905747907;2.784757795351504-i*3.1942103905747907;"
    "3.5585347603474+i*4.1428457169986554;3.5585347603474-i*4.1428457169986554;"
    "2.038584192971233+i*8.726745077486314;2.038584192971233-i*8.726745077486314;"
    "0.7461736023194235+i*11.92095546818733;0.7461736023194235-i*11.92095546818733]"
    ',1,"n")'
)
# FM3 "BounceRoll": notch zeros on the imaginary axis and their pole pairs, DC gain 1.
NOMINAL_FM3 = (
    "zpk([0+i*15.849353127564198;0-i*15.849353127564198;"
    "0+i*15.985447321046138;0-i*15.985447321046138;"
    "0+i*16.19983737166611;0-i*16.19983737166611;"
    "0+i*16.338941081813793;0-i*16.338941081813793;"
    "0+i*23.140320589850464;0-i*23.140320589850464;"
    "0+i*23.26601400048155;0-i*23.26601400048155;"
    "0+i*23.4787668327507;0-i*23.4787668327507;"
    "0+i*23.60629860829092;0-i*23.60629860829092],"
    "[0.5211835443328433+i*15.408608752182579;0.5211835443328433-i*15.408608752182579;"
    "0.058251837358148116+i*15.601957325436517;0.058251837358148116-i*15.601957325436517;"
    "0.06196994001969834+i*16.597791687192313;0.06196994001969834-i*16.597791687192313;"
    "0.5678095655664466+i*16.787090745525184;0.5678095655664466-i*16.787090745525184;"
    "0.36960722373365074+i*22.87824676135586;0.36960722373365074-i*22.87824676135586;"
    "0.0389075111666054+i*23.001902251253206;0.0389075111666054-i*23.001902251253206;"
    "0.04017003191967269+i*23.748286093426035;0.04017003191967269-i*23.748286093426035;"
    "0.38563718208449665+i*23.870482240972727;0.38563718208449665-i*23.870482240972727]"
    ',1,"n")'
)
