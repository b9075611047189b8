"""twind's diagnosis of KAGRA's real measurements, scored against the independent expert
reading of each (``tests/data/kagra/reference.toml``, made by :mod:`twind.lab.kagra_reference`
without twind's model or analysis code).

Each shared file is diagnosed by ``twind diagnose --config <optic>.toml FILE --json`` in a
process of its own, timed, and scored as a bench case is
(:func:`twind.lab.plant_cases.score`): a mode the reference moves by
:data:`SHIFT_PCT` or more, and not ambiguous, is *read* when twind says "the model's mode at X
is at Y" for that model mode with Y within 5 % (every peak of these files is narrower than
two bins), *read as new* when twind claims a mode the model lacks near it instead. The
reference's ambiguous modes are not counted either way. Run with ``twind bench --suite
kagra``.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Sequence
from pathlib import Path

from twind.config import CONFIG_DIR
from twind.config.reader import read_toml
from twind.lab.kagra_reference import DATA
from twind.lab.plant_cases import Score, diagnose_files, score

SHIFT_PCT = 2.0
"""A reference mode shift counted: 2 % or more."""
RESOLUTION_HZ = 2.0**-7
"""The files' Hann bin."""


def reference_modes(entry: dict) -> list[dict]:
    """The reference's modes of one file as :func:`~twind.lab.plant_cases.score` takes a
    case's truth: each with a numeric model counterpart, moved when not ambiguous and
    shifted by :data:`SHIFT_PCT` or more; every Q unresolved (a bin or narrower). A mode
    the model's drive does not reach, which the reference reads as the model's mode of its
    own DOF (``own_dof_model_f``), is a right reading but no shift counted."""
    out = []
    for m in entry.get("modes", []):
        if isinstance(m.get("own_dof_model_f"), float | int):  # no drive of the model
            out.append({"model_f_hz": float(m["own_dof_model_f"]), "true_f_hz": float(m["f"]),
                        "true_q": math.inf, "shift_percent": 0.0, "moved": False})
        if not isinstance(m.get("model_f"), float | int):
            continue
        shift = 100.0 * (m["f"] / m["model_f"] - 1.0)
        out.append({"model_f_hz": float(m["model_f"]), "true_f_hz": float(m["f"]),
                    "true_q": math.inf, "shift_percent": shift,
                    "moved": abs(shift) >= SHIFT_PCT and not m.get("ambiguous", False)})
    return out


def readings(diagnosis: dict) -> list[str]:
    """Each chosen claim's reading, for the printout."""
    return [f"    {c['reading']}" for c in diagnosis.get("effects", [])
            if c.get("rival_of") is None]


def run(names: Sequence[str], workdir: str | Path, timeout_s: float = 600.0,
        say: Callable[[str], object] = print) -> list[str]:
    """Each named file of :data:`DATA` diagnosed and scored, its lines said as it is done.

    Returns
    -------
    list of str
        The totals: shifts read, read as new, claims, and the seconds.
    """
    key = read_toml(DATA / "reference.toml")["files"]
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    scores: list[Score] = []
    for name in names:
        config = CONFIG_DIR / "kagra" / f"{name.split('_')[0]}.toml"
        diagnosis, seconds, error = diagnose_files(config, [DATA / name],
                                                   workdir / Path(name).stem, timeout_s)
        modes = reference_modes(key[name])
        s = (score(diagnosis, modes, RESOLUTION_HZ) if diagnosis is not None
             else Score(moved=sum(m["moved"] for m in modes), error=error))
        s.seconds = seconds
        scores.append(s)
        say(f"{name:28s} {seconds:6.1f} s: " + (f"FAILED: {error}" if error else
            f"shifts {s.moved}: read {s.read}, as new {s.read_as_new}; claims {s.claims}, "
            f"not the reference's {s.wrong} (beyond the coherent band {s.beyond})"))
        for line in [*readings(diagnosis or {}), *(f"    {n}" for n in s.notes)]:
            say(line)
    moved = sum(s.moved for s in scores)
    seconds = [s.seconds for s in scores]
    return [f"files {len(scores)}, failed {sum(bool(s.error) for s in scores)}",
            f"shifts of {SHIFT_PCT:g} % or more: {moved}, read {sum(s.read for s in scores)}, "
            f"read as new {sum(s.read_as_new for s in scores)}",
            f"claims beyond the coherent band: {sum(s.beyond for s in scores)}",
            f"seconds: median {statistics.median(seconds):.1f}, most {max(seconds):.1f}"]
