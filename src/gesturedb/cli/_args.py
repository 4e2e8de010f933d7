"""argparse helpers shared by the commands: types with ranges (a number out of range is a
one-line usage error, never a traceback) and options that several commands take alike."""
from __future__ import annotations

import argparse
import math

from gesturedb.synth.matching import DEFAULT_INIT, INIT_CHOICES


def int_range(lo: int, hi: int):
    """An argparse ``type`` accepting integers in ``[lo, hi]``."""
    def parse(text: str) -> int:
        try:
            v = int(text, 10)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer from {lo} to {hi}, got {text!r}") from None
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"expected an integer from {lo} to {hi}, got {text}")
        return v
    parse.__name__ = "integer"
    return parse


def float_range(lo: float, hi: float):
    """An argparse ``type`` accepting finite numbers in ``[lo, hi]``."""
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number from {lo:g} to {hi:g}, got {text!r}") from None
        if not (math.isfinite(v) and lo <= v <= hi):
            raise argparse.ArgumentTypeError(f"expected a number from {lo:g} to {hi:g}, got {text}")
        return v
    parse.__name__ = "number"
    return parse


def add_init_argument(parser) -> None:
    """``--init``, the search's initial pose, as ``synth`` and ``eval`` take it (its seed is ``--seed``)."""
    parser.add_argument("--init", choices=INIT_CHOICES, default=DEFAULT_INIT,
                        help="initial pose: a database frame drawn with --seed (default, as the paper's "
                        "experiments) or the mean pose")
