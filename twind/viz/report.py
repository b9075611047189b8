"""The report ``twind diagnose -o DIR`` writes: Bode matrices before and after, the JSON, a
Rerun file, and a page with the verdict first, then the tables a commissioner reads (the
nominal parameters, every hypothesis, the rivals and what tells them apart, the bands located
and left), then the figures."""

from __future__ import annotations

import html
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from twind import __version__, strictjson
from twind.analysis.diagnosis import DiagnoseError, Diagnosis
from twind.analysis.estimation.tfset import TFSet
from twind.analysis.prediction import FitCurves
from twind.viz.plotting import plot_fit
from twind.viz.spectra import write_spectra_rrd

if TYPE_CHECKING:  # a type named, not imported: viz draws what the analysis found
    from twind.analysis.identification.locate import Located

STYLE = """
body { font-family: sans-serif; max-width: 70em; margin: 1em auto; color: #222 }
.verdict { font-size: 1.3em; padding: .6em; background: #eef3fb; border-left: .4em solid #36c }
table { border-collapse: collapse; margin: .5em 0 1.2em }
th, td { border: 1px solid #ccc; padding: .2em .6em; text-align: right }
th { background: #f2f2f2 } td:first-child, th:first-child { text-align: left }
tr.claimed td { font-weight: bold }
img { max-width: 100% }
"""


def report_page(diagnosis: Diagnosis, images: Sequence[tuple[str, str]],
                measured: Sequence[tuple[str, str]] = ()) -> str:
    """The HTML page of `diagnosis`: the verdict, the tables, then the figures.

    Parameters
    ----------
    diagnosis : Diagnosis
        As ``twind diagnose`` finds it.
    images : sequence of (str, str)
        The figures as ``(title, file)`` pairs, the file's path relative to the page.
    measured : sequence of (str, str)
        What was measured and how, as ``(what, value)`` rows (:func:`measurement`).

    Returns
    -------
    str
        The page's HTML, every text escaped.
    """
    d = diagnosis
    optic = html.escape(d.nominal.optic)
    parts = [f"<h1>twind diagnose: {optic}</h1>",
             f'<p class="verdict" id="verdict">{html.escape(d.summary())}</p>',
             f"<p>chi2/nu {d.nominal.chi2_nu:.3f} with the nominal model refitted, "
             f"{d.final.chi2_nu:.3f} with the final one ({d.final.bins} bins, coherence "
             f"&gt;= {d.final.min_coherence:g}).</p>"]
    if measured:
        parts += ["<h2>The measurement</h2>", table("measurement", ("", ""), measured)]
    if d.input_matrix is not None:
        parts += ["<h2>The input matrix, measured (IN1 against the OSEM readings)</h2>",
                  _listed("input_matrix", d.input_matrix.lines())]
    if d.controller is not None:
        parts += ["<h2>The damping controller, measured (OUT/IN2)</h2>",
                  _listed("controller", d.controller.lines())]
    parts += ["<h2>Nominal parameters, refitted</h2>", _nominal(d),
             "<h2>Hypotheses</h2>", _hypotheses(d)]
    if d.separations:
        parts += ["<h2>Rivals and the measurement that separates them</h2>", _separations(d)]
    parts += ["<h2>Where the nominal model misses</h2>",
              bands("located", d.located, "none: no band stands out"),
              "<h2>Unexplained by the final model</h2>",
              bands("unexplained", d.unexplained, "nothing")]
    parts += [f'<h2>{html.escape(title)}</h2><img src="{html.escape(src)}" '
              f'alt="{html.escape(title)}">' for title, src in images]
    parts.append('<p><a href="diagnosis.json">diagnosis.json</a>; '
                 "<code>rerun diagnosis.rrd</code> (timeline frequency_hz)</p>")
    return html_page(f"twind diagnose: {optic}", parts)


def html_page(title: str, parts: Sequence[str]) -> str:
    """A report's page: `parts` (HTML) under `title`, in the reports' style."""
    return (f"<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>{html.escape(title)}"
            f"</title><style>{STYLE}</style></head><body>{''.join(parts)}</body></html>")


def report_dir(out: str | Path, names: Sequence[str], error: type[Exception]) -> Path:
    """Folder `out`, made if need be, for a report's files `names`; `error` if it already
    holds any of them: reports are never overwritten."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    taken = [n for n in names if (out / n).exists()]
    if taken:
        msg = f"{out} already holds {', '.join(taken)}; twind does not overwrite reports"
        raise error(msg)
    return out


def table(table_id: str, header: Sequence[str], rows: Sequence[Sequence[str]],
          classes: Sequence[str] | None = None) -> str:
    """An HTML table; cells are escaped, `classes` (one per row) mark rows."""
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join(
        f'<tr class="{c}">' + "".join(f"<td>{html.escape(x)}</td>" for x in row) + "</tr>"
        for row, c in zip(rows, classes or [""] * len(rows), strict=True))
    return f'<table id="{table_id}"><tr>{head}</tr>{body}</table>'


def number(x: float | None, digits: int = 4) -> str:
    """`x` to `digits` significant digits; a dash where it is undetermined."""
    return "—" if x is None or not math.isfinite(x) else f"{x:.{digits}g}"


def _listed(key: str, lines: list[str]) -> str:
    """`lines` as an HTML list with id `key`."""
    return (f'<ul id="{key}">' + "".join(f"<li>{html.escape(line.strip())}</li>" for line in lines)
            + "</ul>")


def _nominal(d: Diagnosis) -> str:
    """The refitted nominal parameters; what the data cannot fix is held at its start."""
    params = d.nominal.to_json()["params"]
    rows = [(p["label"], "held at start" if p["sigma"] is None else number(p["value"], 6),
             number(p["sigma"], 3), "unidentifiable" if p["sigma"] is None else
             f"{100 * p['sigma'] / abs(p['value']):.2g} %", number(p["start"], 6))
            for p in params.values()]
    return (table("nominal", ("parameter", "value", "sigma", "relative", "start"), rows)
            + "<p>A parameter these data cannot fix is held at its start: it has no sigma "
            "(—).</p>")


def _hypotheses(d: Diagnosis) -> str:
    """Every hypothesis of the first step, then the effects chosen later, with their
    p-values, delta BIC and parameters, the claimed ones in bold; then those that gave no
    fit to weigh at any step, with the reason."""
    chosen = {e.effect: e for e in d.effects}
    tried = {e.effect: e for e in d.first_step}
    tried.update(chosen)
    order = sorted(tried.values(), key=lambda e: (e.effect not in chosen, e.p_value))
    rows, classes = [], []
    for e in order:
        own = chosen.get(e.effect, e)
        values, sigma = own.values()
        params = ", ".join(f"{n} {number(v)} ± {number(sigma.get(n), 2)}"
                           for n, v in values.items())
        role = ("rival of " + own.rival_of if own.rival_of else
                "chosen" + (" (partial)" if own.partial else "")) if e.effect in chosen else (
            "not claimed")
        rows.append((e.effect, role, number(own.p_value, 2), number(own.delta_bic, 3),
                     params))
        classes.append("claimed" if e.effect in chosen else "")
    shown = set(tried)
    for x in d.not_fitted:
        if x.effect not in shown:  # one row a hypothesis (later steps' in the JSON)
            shown.add(x.effect)
            rows.append((x.effect, f"not weighed at step {x.step}: {x.reason}", "", "", ""))
            classes.append("")
    return (table("hypotheses", ("hypothesis", "verdict", "p-value", "delta BIC",
                                  "parameters ± sigma"), rows, classes)
            + "<p>delta BIC is the likelihood ratio less ln(bins) per parameter: positive "
            "favours the hypothesis over the model without it. A p-value pays for the "
            "search and for the hypotheses tried (Bonferroni).</p>")


def _separations(d: Diagnosis) -> str:
    rows = [(a, b, m.excite, f"{m.measure}/{m.excite}", f"{m.frequency_hz:.3g}",
             f"{m.amplitude:.3g}", f"{m.seconds:.3g}" if m.separable else
             f"{m.seconds:.2g}: not by loop measurements")
            for (a, b), m in d.separations.items()]
    return table("separations", ("effect", "rival", "excite", "measure", "around (Hz)",
                                 "sine amplitude", "seconds for 3 sigma"), rows)


def bands(table_id: str, located: Sequence[Located], empty: str) -> str:
    """The located bands as a table (`empty` in words where there are none)."""
    if not located:
        return f'<p id="{table_id}">{html.escape(empty)}</p>'
    rows = [(x.element, f"{x.band_hz[0]:.3g}-{x.band_hz[1]:.3g}", f"{x.significance:.1f}",
             f"{x.excess:.2f}") for x in located]
    return table(table_id, ("element", "band (Hz)", "significance (sigma)",
                             "residual power / expected"), rows)


def measurement(tfs: TFSet, inputs: Sequence[str | Path] = ()) -> list[tuple[str, str]]:
    """What a report says of its measurement: the files, the optic and DOFs, the estimate
    (estimator, resolution, averages, band) and the twind that read it."""
    f = tfs.frequency_hz
    rows = [("inputs", ", ".join(Path(p).name for p in inputs))] if inputs else []
    about = tfs.description()
    return [*rows, ("optic", f"{tfs.ifo}:{tfs.optic}"), ("channels", about["channels"]),
            ("GPS", about["GPS"]),
            ("estimate", f"{about['estimate']}, {number(f.min(), 3)}-{number(f.max(), 4)} Hz"),
            ("read by", f"twind {__version__}")]


REPORT_FILES = ("nominal.png", "augmented.png", "diagnosis.json", "index.html",
                "diagnosis.rrd")
"""The files of a diagnosis report (:func:`write_report`)."""


def write_report(diagnosis: Diagnosis, fits: Mapping[str, FitCurves], tfs: TFSet,
                 out: str | Path, inputs: Sequence[str | Path] = ()) -> Path:
    """The report of a diagnosis in directory `out` (created).

    Parameters
    ----------
    diagnosis : Diagnosis
    fits : mapping of str to FitCurves
        Its models on the measurement's grid (:meth:`Diagnosis.curves`): ``"nominal"`` and,
        when an effect was chosen, ``"augmented"``.
    tfs : TFSet
        The measurement it was made from.
    out : path
        The directory: ``nominal.png`` and ``augmented.png`` (measured, model, residual /
        sigma per bin, before and after), ``diagnosis.json``, ``diagnosis.rrd`` and
        ``index.html`` (:func:`report_page`).
    inputs : sequence of path
        The files measured, named in the report.

    Returns
    -------
    Path
        The page.

    Raises
    ------
    DiagnoseError
        If `out` already holds a report's files: reports are never overwritten.
    """
    out = report_dir(out, REPORT_FILES, DiagnoseError)
    for name, fit in fits.items():
        plot_fit(fit, str(out / f"{name}.png"))
    (out / "diagnosis.json").write_text(strictjson.dumps(diagnosis.to_json(), indent=1))
    _write_rrd(fits, out / "diagnosis.rrd", f"twind diagnose {diagnosis.nominal.optic}")
    titles = {"nominal.png": "The nominal model refitted, against the configuration it "
                             "started from: measured, models, coherence, residual / sigma",
              "augmented.png": "With the effects chosen, against the nominal model refitted"}
    images = [(t, n) for n, t in titles.items() if (out / n).exists()]
    (out / "index.html").write_text(report_page(diagnosis, images, measurement(tfs, inputs)))
    return out / "index.html"


def _write_rrd(fits: Mapping[str, FitCurves], path: Path, title: str) -> None:
    """Per element: measured and each fitted model's |IN1/EXC| (dB) and residuals / sigma,
    over the bins the fits used."""
    series = {}
    for label, fit in fits.items():
        f, pred = fit.frequency_hz, fit.fitted
        for i, r in enumerate(fit.responses):
            for j, e in enumerate(fit.excited):
                used = fit.used[:, i, j]
                if not used.any():
                    continue
                base = f"diagnose/{r}_{e}"
                resid = np.abs(fit.H[:, i, j] - pred[:, i, j]) / fit.sigma[:, i, j]
                series[f"{base}/{label}_db"] = (f[used], 20 * np.log10(np.abs(pred[used, i, j])))
                series[f"{base}/{label}_residual_sigma"] = (f[used], resid[used])
                series.setdefault(f"{base}/measured_db",
                                  (f[used], 20 * np.log10(np.abs(fit.H[used, i, j]))))
    write_spectra_rrd(path, title, series)
