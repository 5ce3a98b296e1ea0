"""The one progress helper of the command line: rich bars on a terminal, plain lines in logs.

Progress is not a result: the bar and the lines go to stderr, so a verb's stdout carries only its
results (``diagnose --json | python -c 'import json, sys; json.load(sys.stdin)'`` parses).
On a terminal a transient rich bar shows the task (with ``done/total`` and the time left once the
total is known: given at the start, or by the first update that gives one, as for a fit whose
length is known only once the data are read); when stderr is not a terminal (CI logs, files,
pipes) the same updates print plain lines ``label: done/total (elapsed s)`` at most every
:data:`PLAIN_EVERY_S` seconds, plus the first and the last, and ``label: done (elapsed s)`` at the
end, so a log shows that work goes on and how long it took.

A bar always ends at its total: when the work ends short of the declared total (an early stop, a
cached or skipped step, a total that was only an estimate), the count it reached becomes the total,
so the last count line reads ``174/174``, not ``174/532`` followed by ``done``.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    Task,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.text import Text

PLAIN_EVERY_S = 10.0
console = Console(stderr=True)  # progress, never results: stdout stays for what a verb prints as its result


class _Count(MofNCompleteColumn):
    """``done/total``, blank while the total is unknown (rich would show ``done/?``)."""

    def render(self, task: Task) -> Text:
        return super().render(task) if task.total is not None else Text("")


def note(message: str) -> None:
    """Print one progress message (a step done, a count traced) where progress goes: stderr, as written."""
    console.print(message, highlight=False, markup=False, soft_wrap=True)


@contextlib.contextmanager
def progress(label: str, total: int | None = None) -> Iterator[Callable[..., None]]:
    """Yield ``update(done, total=None, label=None)`` that reports progress of a long verb.

    Args:
        label: what is being done (the bar's text, the plain lines' prefix).
        total: number of steps, or None when unknown (a spinner; plain lines show elapsed time).
    """
    start = time.perf_counter()
    if console.is_terminal:
        counts = (_Count(), TimeRemainingColumn())  # both blank until a total is known
        columns = (TextColumn("[bold]{task.description}"), BarColumn(), *counts, TimeElapsedColumn())
        with Progress(*columns, console=console, transient=True) as bar:
            task = bar.add_task(label, total=total)

            def update(done: int, total: int | None = None, label: str | None = None) -> None:
                bar.update(
                    task,
                    completed=done,
                    **({"total": total} if total else {}),
                    **({"description": label} if label else {}),
                )

            yield update
            reached = bar.tasks[0]
            if reached.total and reached.completed < reached.total:  # ended short: what it reached was the total
                bar.update(task, total=reached.completed)
        return
    state = {"last": -float("inf"), "label": label, "total": total, "done": None}

    def plain(done: int, total: int | None = None, label: str | None = None) -> None:
        state["label"], state["total"], state["done"] = label or state["label"], total or state["total"], done
        now = time.perf_counter()
        if now - state["last"] >= PLAIN_EVERY_S or (state["total"] and done >= state["total"]):
            count = f"{done}/{state['total']}" if state["total"] else f"{done}"
            console.print(f"{state['label']}: {count} ({now - start:.0f} s)", highlight=False)
            state["last"] = now

    yield plain
    reached, elapsed = state["done"], time.perf_counter() - start
    if state["total"] and reached is not None and reached < state["total"]:  # ended short: it reached its total
        console.print(f"{state['label']}: {reached}/{reached} ({elapsed:.0f} s)", highlight=False)
    console.print(f"{label}: done ({elapsed:.0f} s)", highlight=False)
