"""The result tables the verbs print, kept readable in an 80-column terminal.

rich shares a narrow terminal among a table's columns and cuts what does not fit with "…". The
verbs' tables therefore have few columns, short headers that may wrap (units and meanings go in the
caption), a label column that stays on one line, and figure columns at least :data:`FIGURE_WIDTH`
wide, so that no figure is ever cut.
"""

from __future__ import annotations

from rich.table import Table

from mi_lidar.core.decimals import fixed

FIGURE_WIDTH = 6  # "12.345": a figure column never gets narrower


def figure(value: float, digits: int = 3) -> str:
    """A table figure; "-" where there is nothing to score (no measured miss among the test beams, say).

    Args:
        value: the figure, in the unit its column's header or the caption gives.
        digits: decimals after the point; a value that rounds to zero prints without a minus sign.
    """
    return fixed(value, digits) if value == value else "-"


def figure_table(title: str, label: str, columns, caption: str | None = None) -> Table:
    """A table of one label column (``label``, on one line) and right-justified figure columns.

    Args:
        title: the table's title.
        label: header of the first column (a model, a simulator, an application).
        columns: headers of the figure columns; a header may wrap, its figures never.
        caption: what the headers abbreviate, their units.
    """
    table = Table(title=title, caption=caption, header_style="bold")
    table.add_column(label, no_wrap=True)
    for column in columns:
        table.add_column(column, justify="right", min_width=FIGURE_WIDTH)
    return table


def rows_table(title: str, label: str, columns, rows, caption: str | None = None) -> Table:
    """A :func:`figure_table` with one row per dict of ``rows``: its ``"model"``, then a figure per column.

    Args:
        title: the table's title.
        label: header of the first column.
        columns: ``(header, key)`` of each figure column: the figure is the row's value at ``key``.
        rows: dicts holding ``"model"`` and every column's key (a benchmark's rows).
        caption: what the headers abbreviate, their units.
    """
    table = figure_table(title, label, [header for header, _ in columns], caption)
    for row in rows:
        table.add_row(row["model"], *(figure(row[key]) for _, key in columns))
    return table
