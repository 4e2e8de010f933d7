"""Text tables that fit a terminal: what ``gesturedb eval`` prints and writes to ``metrics.txt``.

A table wider than `TEXT_WIDTH` columns is cut into several narrower tables stacked one
under another, each repeating the first (label) column, so every number stays next to
its row's name without wrapping. The JSON and HTML reports keep the whole table in one.
"""
from __future__ import annotations

from collections.abc import Sequence

__all__ = ["TEXT_WIDTH", "text_table"]

#: Widest line of a printed table, in characters: a terminal of 100 columns shows every line
#: unwrapped (at 80 most metric tables would come in three parts instead of two).
TEXT_WIDTH = 100
#: Spaces between two columns.
_GAP = "  "


def _column_parts(widths: Sequence[int], width: int) -> list[list[int]]:
    """Indices of the value columns (1, 2, ...) of each part: as few parts as fit beside the label
    column, sharing the columns evenly where they fit so (not five parts of six and one of two)."""
    def fits(cols):
        return len(cols) == 1 or widths[0] + sum(len(_GAP) + widths[i] for i in cols) <= width

    greedy: list[list[int]] = []
    for i in range(1, len(widths)):
        if greedy and fits(greedy[-1] + [i]):
            greedy[-1].append(i)
        else:
            greedy.append([i])  # a column too wide for any part gets one of its own
    if not greedy:
        return []
    size, more = divmod(len(widths) - 1, len(greedy))
    even, start = [], 1
    for k in range(len(greedy)):
        n = size + (k < more)
        even.append(list(range(start, start + n)))
        start += n
    return even if all(fits(cols) for cols in even) else greedy


def text_table(head: Sequence[str], body: Sequence[Sequence[str]], *, width: int = TEXT_WIDTH,
               align: str = "right") -> str:
    """Aligned text columns with a rule under the head, in parts no wider than ``width``.

    Parameters
    ----------
    head : sequence of str [length C]
        Column headers; the first column holds the row labels.
    body : sequence of sequence of str [shape=(R, C)]
        Cells, already formatted.
    width : int
        Widest line of a part, characters (default `TEXT_WIDTH`). A label column and one
        value column wider than this still make one part.
    align : {"right", "left"}
        Value columns right-aligned (numbers) or left-aligned (text); labels are left-aligned.

    Returns
    -------
    str
        One table, or several separated by a blank line, each repeating the label column;
        no line ends in spaces.
    """
    if align not in ("right", "left"):
        raise ValueError(f"align: expected 'right' or 'left', got {align!r}")
    widths = [max(len(h), *(len(row[i]) for row in body)) for i, h in enumerate(head)]

    def line(cells, cols):
        out = [cells[0].ljust(widths[0])]
        out += [cells[i].rjust(widths[i]) if align == "right" else cells[i].ljust(widths[i]) for i in cols]
        return _GAP.join(out).rstrip()

    tables = []
    for cols in _column_parts(widths, width) or [[]]:
        rows = [line(head, cols), line(["-" * w for w in widths], cols)] + [line(row, cols) for row in body]
        tables.append("\n".join(rows))
    return "\n\n".join(tables)
