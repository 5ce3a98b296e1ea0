"""Stray text in a scene XML: refused, because Mitsuba's parser skips it without a word.

A Mitsuba scene is elements and attributes only; its parser ignores any text between elements. A typo
that turns an element into text therefore loses it silently: ``&lt;float name="p_hit" value="0.3"/>``,
``>float ...`` or ``float ...`` (its ``<`` lost) leave the material at ``p_hit`` 1 with no message, and
``x<float .../>`` or a word left after ``</scene>`` loads as if it were not there. The checker reads the
file with expat (which knows lines and columns) and refuses the first text that is not whitespace,
naming the line, the column, the text and the element it sits in.
"""

from __future__ import annotations

import xml.parsers.expat as expat

from mi_lidar.core.errors import SceneError

SHOWN_CHARS = 40  # how much of a stray text the message quotes
FIX = (
    "a Mitsuba scene holds only elements, so Mitsuba ignores this text without a word, and a property written "
    "without its '<' is lost: remove the text, or restore the element's '<'"
)


def check_stray_text(text: str, where: str) -> str | None:
    """Refuse a scene XML holding text that is not whitespace inside its elements.

    Args:
        text: the file's content.
        where: the file, for the message.

    Returns:
        None for a clean file; a message for text before or after the root element that expat refuses, which
        the caller raises only when Mitsuba's own parser loads the file (else Mitsuba's syntax error is the
        better message).

    Raises:
        SceneError: non-whitespace text (or CDATA) inside an element, naming the file, line, column, the text
            and the enclosing element.
    """
    parser = expat.ParserCreate()
    open_tags: list[str] = []
    found: list[tuple[int, int, str, str]] = []  # (line, column, text, element): the first stray text
    pending: list[str] = []  # text since the last tag
    start = [0, 0]  # line and column (from 1) of its first visible character
    started = []  # a sign that the root element began

    def flush():
        piece = "".join(pending).strip()
        if piece and not found:
            found.append((start[0], start[1], piece, open_tags[-1]))
        pending.clear()

    def on_text(data):
        if not "".join(pending).strip() and data.strip():  # where the text's first visible character is
            lead = data[: len(data) - len(data.lstrip())]
            column = len(lead) - lead.rfind("\n") if "\n" in lead else parser.CurrentColumnNumber + len(lead) + 1
            start[:] = parser.CurrentLineNumber + lead.count("\n"), column
        pending.append(data)

    def on_start(tag, attributes):
        flush()
        started.append(True)
        shown = " ".join(f'{k}="{v}"' for k, v in list(attributes.items())[:2])
        open_tags.append(f"<{tag}{' ' + shown if shown else ''}>")

    def on_end(_):
        flush()
        open_tags.pop()

    parser.CharacterDataHandler, parser.StartElementHandler, parser.EndElementHandler = on_text, on_start, on_end
    try:
        parser.Parse(text, True)
    except expat.ExpatError as exc:
        if open_tags:
            flush()  # text just before the error (``x<<float``)
        after = exc.code == expat.errors.codes[expat.errors.XML_ERROR_JUNK_AFTER_DOC_ELEMENT]
        if found or (started and not after):
            return _raise(where, found)  # inside the root: Mitsuba reports the syntax error in its own words
        lines = text.splitlines()
        line = lines[exc.lineno - 1] if exc.lineno <= len(lines) else ""
        piece = line[exc.offset :] if after else line
        return (
            f"{where}: line {exc.lineno}, column {exc.offset + 1}: text outside the root element {_shown(piece)}; {FIX}"
        )
    return _raise(where, found)


def _raise(where: str, found: list[tuple[int, int, str, str]]) -> None:
    """Raise the SceneError of the first stray text found, if any."""
    if found:
        line, column, piece, element = found[0]
        raise SceneError(f"{where}: line {line}, column {column}: stray text {_shown(piece)} in {element}; {FIX}")


def _shown(piece: str) -> str:
    """A stray text for a message: quoted, its line breaks folded, cut at :data:`SHOWN_CHARS`."""
    piece = " ".join(piece.split())
    return repr(piece if len(piece) <= SHOWN_CHARS else piece[:SHOWN_CHARS] + "...")
