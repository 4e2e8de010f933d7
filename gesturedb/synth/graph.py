"""GestureMaster (Zhou et al. 2022, Sec. 4): speech -> gestures by a path through the motion graph."""
from __future__ import annotations

from gesturedb.synth.viterbi import viterbi

__all__ = ["viterbi"]
