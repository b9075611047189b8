"""``twind bench --suite freeswing``: the free-swinging health check on the ringdowns of random
drifted optics with OSEM imbalances, against each optic's own eigenmodes."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace

import numpy as np

from twind import DOFS, progress
from twind.analysis.identification.freeswing import analyse, eigenmodes, ringdown
from twind.channels import OSEMS
from twind.config import OpticConfig
from twind.model.effects import with_effect


def benchmark(optic: OpticConfig, n: int = 8, duration_s: float = 1000.0, seed: int = 0
              ) -> Iterator[str]:
    """:func:`analyse` on the ringdowns of `n` random optics: each drifted from `optic`
    (wire length +-4 %, break-off +-20 %, clamp separation +-10 %, Qs 250-800) with face
    OSEM gains off by up to +-10 %, analysed with the nominal model. Lines: per optic, the
    worst frequency error against the drifted optic's eigenfrequencies (mHz), the worst Q
    error (%), the worst OSEM gain error (% of each imbalance), the largest error in
    standard errors and the largest difference of the two halves (:attr:`FreeSwing.halves`),
    as each optic is done; then the worst of all and the RMS of the errors in standard
    errors (1 when the standard errors are right).

    Parameters
    ----------
    optic : OpticConfig
        The nominal optic: the drifts' centre and the analysis's model.
    n : int
        Random optics rung down.
    duration_s : float
        Length of each ringdown (s).
    seed : int
        Seed of the drifts; optic ``k``'s ringdown noise uses ``seed + k``.

    Yields
    ------
    str
        One line per optic, then the two summary lines.
    """
    rng = np.random.default_rng(seed)
    worst, pulls = np.zeros(3), []
    for k in range(n):
        sus = optic.sus.updated(
            wire_length_m=optic.sus.wire_length_m * rng.uniform(0.96, 1.04),
            b_m=optic.sus.b_m * rng.uniform(0.8, 1.2), R1_m=optic.sus.R1_m * rng.uniform(0.9, 1.1),
            Q={d: float(rng.uniform(250, 800)) for d in DOFS})
        real = replace(optic, sus=sus)
        imbalance = {f"gain_{o}": float(rng.uniform(-0.1, 0.1)) for o in OSEMS[:4]}
        plant = with_effect(real.loop().plant, sus, "osem_imbalance", imbalance)
        sen, rate = ringdown(real, duration_s, seed=seed + k, plant=plant)
        found = analyse(optic, sen, rate)
        f_true, q_true = eigenmodes(real, plant)
        df = max(abs(found.frequency_hz[d] - f_true[d]) for d in DOFS)
        q_err = {d: abs(found.q[d] / q_true[d] - 1) for d in DOFS}
        worst_q = max(q_err, key=q_err.get)
        pulls.append([(found.frequency_hz[d] - f_true[d]) / found.frequency_sigma_hz[d]
                      for d in DOFS] + [(found.q[d] - q_true[d]) / found.q_sigma[d] for d in DOFS])
        true_g = np.array([1 + imbalance[f"gain_{o}"] for o in OSEMS[:4]])
        true_g /= true_g.mean()
        got = np.array([found.osem_gains[o] for o in OSEMS[:4]])
        dg = np.max(np.abs((got - 1) - (true_g - 1)) / np.abs(true_g - 1))
        worst = np.maximum(worst, [df, q_err[worst_q], dg])
        gap = 1e3 * abs(f_true["POS"] - f_true["SIDE"])
        halves = ("too short to halve" if found.halves is None else "halves within "
                  f"{max(abs(x) for p in found.halves.values() for x in p):.1f} sigma")
        progress.tick()
        yield (f"optic {k + 1}: frequencies within {1e3 * df:.3f} mHz, Qs within "
               f"{100 * q_err[worst_q]:.1f} % ({worst_q}), OSEM gain imbalances within "
               f"{100 * dg:.0f} %, errors within {np.max(np.abs(pulls[-1])):.1f} sigma, "
               f"{halves}; POS-SIDE {gap:.1f} mHz apart")
    pulls_f, pulls_q = np.array(pulls)[:, :4], np.array(pulls)[:, 4:]
    yield (f"worst of {n}: {1e3 * worst[0]:.3f} mHz (target 1), Q {100 * worst[1]:.1f} % "
           f"(target 20), OSEM gains {100 * worst[2]:.0f} % (target 35)")
    yield (f"errors in standard errors over {pulls_f.size} modes, RMS (1 if the standard "
           f"errors are right): frequencies {np.sqrt(np.mean(pulls_f**2)):.2f}, "
           f"Qs {np.sqrt(np.mean(pulls_q**2)):.2f}")
