"""The small Markdown subset of mi-lidar's reports (headings, tables, images, bold) as one HTML page."""

from __future__ import annotations

import html
import re

import numpy as np

CELL_SEPARATOR = re.compile(r"(?<!\\)\|")  # a `|` that is not escaped as `\|`


def markdown_to_html(md: str, title: str) -> str:
    """Render the small Markdown subset of our reports (headings, tables, images, bold) as HTML."""
    body, table = [], []

    def flush():
        if table:
            rows = [r for r in table if not set(r.replace("|", "").strip()) <= {"-"}]
            cells = [
                [html.escape(c.strip().replace("\\|", "|")) for c in CELL_SEPARATOR.split(r.strip()[1:-1])]
                for r in rows
            ]
            body.append(
                "<table><tr>"
                + "".join(f"<th>{c}</th>" for c in cells[0])
                + "</tr>"
                + "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in cells[1:])
                + "</table>"
            )
            table.clear()

    for line in md.splitlines():
        if line.startswith("|"):
            table.append(line)
            continue
        flush()
        if line.startswith("#"):
            level = len(line) - len(line.lstrip("#"))
            body.append(f"<h{level}>{html.escape(line.lstrip('#').strip())}</h{level}>")
        elif line.startswith("![") and "](" in line and line.rstrip().endswith(")"):
            # the alt text may hold brackets and parentheses (an effect's name and options): the link
            # is what follows the last "](" up to the closing parenthesis
            alt, src = line.rstrip()[2:-1].rsplit("](", 1)
            body.append(f'<p><img src="{html.escape(src)}" alt="{html.escape(alt)}" style="max-width:100%"></p>')
        elif line.strip():
            text = html.escape(line)
            parts = text.split("**")
            text = "".join(f"<b>{p}</b>" if i % 2 else p for i, p in enumerate(parts))
            body.append(f"<p>{text.replace('`', '')}</p>")
    flush()
    style = (
        "body{font-family:sans-serif;max-width:1100px;margin:auto} table{border-collapse:collapse;font-size:13px}"
        "td,th{border:1px solid #ccc;padding:2px 6px;text-align:right} th{background:#eee}"
    )
    return (
        f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
        f"<style>{style}</style></head><body>{''.join(body)}</body></html>\n"
    )


def table_cell(text) -> str:
    """``text`` as a Markdown table cell: ``|`` escaped (``mean |range error|`` would split the row)."""
    return str(text).replace("|", "\\|")


LISTED = 8  # a list of more numbers reads as its summary (:func:`spread`): 180 per-beam values are a wall of digits


def words(key) -> str:
    """A JSON key or column name as words: ``mean_before`` -> ``mean before``."""
    return str(key).replace("_", " ")


def spread_figures(values) -> dict[str, float]:
    """``{"min", "median", "max", "RMS"}`` of ``values`` (any shape, NaN where there is none)."""
    a = np.asarray(values, dtype=np.float64).ravel()
    if a.size == 0:
        return dict.fromkeys(("min", "median", "max", "RMS"), float("nan"))
    return {"min": a.min(), "median": np.median(a), "max": a.max(), "RMS": np.sqrt(np.mean(a**2))}


def spread(values) -> str:
    """Many numbers in one line: ``180 values: min 0.0312, median 0.0359, max 0.0402, RMS 0.036``."""
    size = np.size(values)
    figures = ", ".join(f"{k} {plain(float(v))}" for k, v in spread_figures(values).items())
    return f"{size:,} values: {figures}" if size else "no values"


def p_value(p: float, digits: int = 2) -> str:
    """A p-value for a table: ``2.3e-50``; ``< 1e-300`` where it underflowed to 0 (it printed as ``0``)."""
    return "< 1e-300" if p == 0 else f"{p:.{digits}g}"


def p_phrase(p: float, digits: int = 2) -> str:
    """A p-value in a sentence: ``p = 2.3e-50``, ``p < 1e-300``."""
    value = p_value(p, digits)
    return f"p {value}" if value.startswith("<") else f"p = {value}"


def plain(value) -> str:
    """A JSON-like value as short readable text for a report: floats to 4 significant digits, lists
    joined by commas (a list of more than :data:`LISTED` numbers as its :func:`spread`), mappings as
    ``key: value`` pairs (:func:`words` for the keys; a nested mapping in brackets). numpy arrays and
    scalars read as lists and numbers."""
    if isinstance(value, (np.ndarray, np.generic)):
        value = value.tolist()
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, dict):
        pairs = ((words(k), f"({plain(v)})" if isinstance(v, dict) else plain(v)) for k, v in value.items())
        return "; ".join(f"{k}: {v}" for k, v in pairs)
    if isinstance(value, (list, tuple)):
        numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        if numbers and len(value) > LISTED:
            return f"[{spread(value)}]"
        return "[" + ", ".join(plain(v) for v in value) + "]"
    return str(value)


def effects_text(effects) -> str:
    """Effects (objects with ``name`` and ``named_values()``, e.g. :class:`~mi_lidar.core.effects.Effect`) as report
    text: ``range_bias (bias: [180 values: min ..., RMS ...]), outliers (rate: 0.01)``; ``none`` for none.
    Their full values are what ``describe()`` writes into scene XML."""
    return ", ".join(f"{e.name} ({plain(e.named_values())})" for e in effects) or "none"
