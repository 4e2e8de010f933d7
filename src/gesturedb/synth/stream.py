"""Live synthesis: the k-NN search as the speech arrives (issue 39).

A :class:`Stream` takes speech in chunks of any size and gives back the output frames
as soon as no later audio can change them::

    stream = Stream(db, SearchOptions(control="left_wrist_high"), sample_rate=16000)
    for chunk in microphone():                   # float32 mono in [-1, 1]
        out = stream.push(chunk)                 # StreamChunk: out.start, out.motion, out.steps
        stream.set_control("slow")               # from the next step on
    last = stream.finish()

:meth:`gesturedb.synth.Searcher.synthesize` is this stream fed the whole file, so the
two cannot drift: the same speech and options give the same frames, bit for bit.

What a frame waits for (:attr:`Stream.latency_s`, the algorithmic latency):

* the search step that contains it: N frames (:data:`gesturedb.search.STEP_FRAMES`,
  8 at 15 fps, 0.53 s), as a step needs the audio features of all its frames;
* the audio features' context: half an FFT window after the frame's end (16 ms at 16 kHz,
  :class:`gesturedb.features.audio.AudioFeatureStream`);
* the feet (:class:`gesturedb.synth.contacts.FootPlanter`): whether a foot is planted is
  known :data:`gesturedb.synth.contacts.MAX_FILL_GAP_S` after the frame, and a step of the
  planted foot needs the motion up to its end (``STEP_S``, 0.67 s).

Placement, the pulls and the seams are causal (:class:`gesturedb.synth.assemble.PieceAssembler`).
The Savitzky-Golay smoothing (``smooth=True``) needs frames on both sides and is refused,
as is a refiner (it refines a whole utterance): synthesize the file for those.
"""
from __future__ import annotations

# Stream is the k-NN search itself (Searcher.synthesize is a stream fed the whole file), so it lives
# beside Searcher in gesturedb.synth.matching; this module is its name.
from gesturedb.synth.matching import Stream, StreamChunk

__all__ = ["Stream", "StreamChunk"]
