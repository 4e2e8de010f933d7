"""Synthesis: speech -> gesture motion by searching an open database.

=================  ==========================================================
``methods``        the registry of synthesis methods (k-NN, graph) that the CLI, eval and server read;
                   ``protocol``: the contract a method keeps
``options``        :class:`SynthOptions`, :class:`SearchOptions`: a synthesis's options, named defaults
``inputs``         what every method does with its speech: samples, minimum length, query
                   features, control masks per step, excluded recordings
``matching``       :class:`Searcher`: Habibie et al. k-NN motion matching
``stream``         :class:`Stream`: the k-NN search as speech arrives (``Searcher.stream``);
                   ``Searcher.synthesize`` is a stream fed the whole file
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
from gesturedb.synth.inputs import MIN_SPEECH_S
from gesturedb.synth.matching import Searcher
from gesturedb.synth.options import SearchOptions, SynthOptions
from gesturedb.synth.result import SynthResult
from gesturedb.synth.stream import Stream, StreamChunk

__all__ = ["Searcher", "SearchOptions", "Stream", "StreamChunk", "SynthOptions", "SynthResult", "MIN_SPEECH_S",
           "savgol_smooth"]
