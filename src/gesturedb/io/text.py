"""Text files users write by hand (word lists, mask files, TSV transcripts): one reader for their lines."""
from __future__ import annotations

from gesturedb.errors import InputFileError

__all__ = ["read_text_lines"]


def read_text_lines(path) -> list[str]:
    """The lines of a UTF-8 text file (a leading BOM, as Excel and some editors write, is dropped).

    Raises
    ------
    InputFileError
        The file cannot be read or is not UTF-8 text.
    """
    try:
        with open(path, "r", encoding="utf-8-sig") as f:
            return f.read().splitlines()
    except (OSError, UnicodeError) as exc:
        raise InputFileError(path, f"cannot read as text: {exc}") from None
