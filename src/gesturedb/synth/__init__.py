"""Synthesis: speech -> gesture motion by searching an open database.

=================  ==========================================================
``matching``       :class:`Searcher`: Habibie et al. k-NN motion matching
``assemble``       pieces of source motion -> one Motion (placement, seams, smoothing)
``result``         :class:`SynthResult`: the motion and its provenance
``graph``          :class:`GraphSynthesizer`: GestureMaster motion-graph search;
                   ``viterbi`` (from ``viterbi``), the exact path search
=================  ==========================================================

    from gesturedb.synth import Searcher
    result = Searcher(gesturedb.open("scott.h5")).synthesize("speech.wav")
"""
from __future__ import annotations

from gesturedb.synth.assemble import savgol_smooth
from gesturedb.synth.matching import Searcher
from gesturedb.synth.result import SynthResult

__all__ = ["Searcher", "SynthResult", "savgol_smooth"]
