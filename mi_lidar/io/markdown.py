"""The small Markdown subset of mi-lidar's reports (headings, tables, images, bold) as one HTML page."""

from __future__ import annotations

import html
import re

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


def plain(value) -> str:
    """A JSON-like value as short readable text for a report: floats to 4 significant digits, lists
    joined by commas, mappings as ``key: value`` pairs (underscores shown as spaces; a nested mapping in brackets)."""
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, dict):
        pairs = (
            (str(k).replace("_", " "), f"({plain(v)})" if isinstance(v, dict) else plain(v)) for k, v in value.items()
        )
        return "; ".join(f"{k}: {v}" for k, v in pairs)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(plain(v) for v in value) + "]"
    return str(value)
