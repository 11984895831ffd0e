"""The HTML page of a calibration report: PNG figures beside one ``report.html``."""

from __future__ import annotations

import datetime
import html
import numbers
import re
import sys
from pathlib import Path
from typing import Mapping, Sequence

from matplotlib.figure import Figure

from ..errors import PdvcError
from ..io import atomic_path, atomic_write_text

__all__ = ["ReportError", "write_report", "REPORT_DPI"]

#: Resolution of the saved PNG figures (dots per inch).
REPORT_DPI = 110

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")

_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Helvetica, Arial, sans-serif;
       max-width: 1100px; margin: 1.5em auto; padding: 0 1em; color: #222; line-height: 1.4; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; }
h2 { font-size: 1.2em; border-bottom: 1px solid #ccc; padding-bottom: 0.2em; margin-top: 1.6em; }
.meta { color: #666; font-size: 0.9em; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.7em; text-align: left; }
th { background: #f2f2f2; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
figure { margin: 0.8em 0; }
figure img { max-width: 100%; height: auto; border: 1px solid #eee; }
figcaption { color: #555; font-size: 0.9em; }
ul.notes li { margin: 0.2em 0; }
""".strip()


class ReportError(PdvcError, ValueError):
    """Inconsistent report content (bad figure name, unknown section...)."""


def _pdvc_version() -> str:
    pkg = sys.modules.get("pdvc")
    version = getattr(pkg, "__version__", None)
    if version:
        return str(version)
    try:
        from importlib.metadata import PackageNotFoundError, version as _meta_version

        return _meta_version("pdvc")
    except PackageNotFoundError:
        return "unknown"


def _format_value(value) -> tuple[str, bool]:
    """Text of a cell and whether it is numeric (right-aligned)."""
    if isinstance(value, str):
        return value, False
    if isinstance(value, (bool,)) or type(value).__name__ == "bool_":
        return str(bool(value)), False
    if isinstance(value, numbers.Integral):
        return str(int(value)), True
    if isinstance(value, numbers.Real):
        return f"{float(value):.6g}", True
    return str(value), False


def _cell(tag: str, value) -> str:
    text, numeric = _format_value(value)
    cls = ' class="num"' if numeric and tag == "td" else ""
    return f"<{tag}{cls}>{html.escape(text)}</{tag}>"


def _table_html(header: Sequence, rows: Sequence[Sequence]) -> str:
    lines = ["<table>"]
    if header is not None and len(header):
        lines.append("<thead><tr>" + "".join(_cell("th", h) for h in header) + "</tr></thead>")
    lines.append("<tbody>")
    for row in rows:
        lines.append("<tr>" + "".join(_cell("td", v) for v in row) + "</tr>")
    lines.append("</tbody></table>")
    return "\n".join(lines)


def _close(fig: Figure) -> None:
    """Release a figure: drop it from pyplot's registry if pyplot made it, then clear it."""
    plt = sys.modules.get("matplotlib.pyplot")
    if plt is not None:
        plt.close(fig)
    fig.clear()


def write_report(
    out_dir,
    *,
    title: str,
    summary: Mapping[str, str | float],
    figures: Mapping[str, Figure],
    tables: Mapping[str, tuple[Sequence, Sequence[Sequence]]] | None = None,
    sections: Sequence[str] | None = None,
    notes: Sequence[str] = (),
    captions: Mapping[str, str] | None = None,
    dpi: int = REPORT_DPI,
    inputs: Sequence[str] = (),
) -> Path:
    """Save the figures as PNG files and write ``report.html`` beside them.

    Parameters
    ----------
    out_dir : path-like
        Output folder, created if missing.  Files of the same names are
        replaced; nothing else in the folder is touched.
    title : str
        Page title.
    summary : mapping of str to str or number
        Key figures (χ, mean SNR before/after, entropy, gauge...), shown first
        as a two-column table; floats with 6 significant digits.
    figures : mapping of str to Figure
        Each saved as ``<name>.png`` (``dpi``) and closed (pyplot's registry
        too, if pyplot created it).  Names are file stems: letters, digits,
        ``_``, ``-``, ``.``, starting with a letter or digit.
    tables : mapping of str to (header, rows), optional
        Extra tables, e.g. from :func:`~pdvc.report.snr_modes_table`.
    sections : sequence of str, optional
        Order of the sections; each name is a key of ``figures`` and/or
        ``tables`` (a name in both shows the figure then the table).  Names
        not listed follow in their mapping order (figures, then tables), so
        nothing is dropped.  Default: figures, then tables.
    notes : sequence of str
        Free-text remarks (the motion summary, unobservable directions...),
        listed last under the heading "What moved".
    captions : mapping of str to str, optional
        Caption of a figure or table, by name.
    dpi : int
        Resolution of the PNG files.
    inputs : sequence of str
        What was read and assumed about the input data (the data kind and
        why, flats, air level, bad pixels, binning...: ``Scan.notes`` of
        :func:`pdvc._inputs.load_scan`), listed after the summary under the heading
        "Inputs".

    Returns
    -------
    Path
        Path of ``report.html``.

    Notes
    -----
    Every file is written atomically; the PNG files first, ``report.html``
    last, so a page never points at a missing or half-written figure.  All
    text is HTML-escaped.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tables = dict(tables or {})
    captions = dict(captions or {})
    figures = dict(figures)
    for name in list(figures) + list(tables):
        if not isinstance(name, str) or not _NAME.match(name) or name == "report":
            raise ReportError(
                f"figure and table names must match {_NAME.pattern} and not be 'report', got {name!r}"
            )
    for name, fig in figures.items():
        if not isinstance(fig, Figure):
            raise ReportError(f"figures[{name!r}] must be a matplotlib Figure, got {type(fig).__name__}")
    order: list[str] = []
    if sections is not None:
        for name in sections:
            if name not in figures and name not in tables:
                raise ReportError(
                    f"section {name!r} is neither a figure nor a table; known: {sorted(set(figures) | set(tables))}"
                )
            if name not in order:
                order.append(name)
    for name in list(figures) + list(tables):
        if name not in order:
            order.append(name)

    try:
        for name, fig in figures.items():
            with atomic_path(out / f"{name}.png") as tmp:
                fig.savefig(tmp, format="png", dpi=dpi)
    finally:
        for fig in figures.values():
            _close(fig)

    now = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
    version = _pdvc_version()
    esc = html.escape
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en">',
        "<head>",
        '<meta charset="utf-8">',
        f"<title>{esc(title)}</title>",
        f"<style>\n{_CSS}\n</style>",
        "</head>",
        "<body>",
        f"<h1>{esc(title)}</h1>",
        f'<p class="meta">generated {esc(now)} by pdvc {esc(version)}</p>',
        "<h2>Summary</h2>",
        _table_html(("quantity", "value"), [(k, v) for k, v in summary.items()]),
    ]
    if inputs:
        parts.append('<section id="inputs">')
        parts.append("<h2>Inputs: what was read and assumed</h2>")
        parts.append('<ul class="notes">')
        parts.extend(f"<li>{esc(str(n))}</li>" for n in inputs)
        parts.append("</ul>")
        parts.append("</section>")
    for name in order:
        parts.append(f'<section id="{esc(name)}">')
        parts.append(f"<h2>{esc(name.replace('_', ' '))}</h2>")
        if name in figures:
            parts.append("<figure>")
            parts.append(f'<img src="{esc(name)}.png">')
            if name in captions:
                parts.append(f"<figcaption>{esc(captions[name])}</figcaption>")
            parts.append("</figure>")
        if name in tables:
            header, rows = tables[name]
            if name in captions and name not in figures:
                parts.append(f"<p>{esc(captions[name])}</p>")
            parts.append(_table_html(header, rows))
        parts.append("</section>")
    if notes:
        parts.append("<h2>What moved</h2>")
        parts.append('<ul class="notes">')
        parts.extend(f"<li>{esc(str(n))}</li>" for n in notes)
        parts.append("</ul>")
    parts += ["</body>", "</html>", ""]
    path = out / "report.html"
    atomic_write_text(path, "\n".join(parts))
    return path
