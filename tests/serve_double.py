"""A stand-in for gesturedb.synth.stream.Stream in the server's tests (never shipped).

It follows the agreed interface (push / push_words / set_control / finish, fps,
sample_rate, latency_s; chunks with start, motion, steps) and replays database
frames in order, one step of N frames as soon as the audio covers it (so its first
frame waits latency_s = N / fps), so that the server's path can be tested before and apart
from the real synthesizer. Its provenance names the control in force at each
step, as the real one does.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gesturedb.errors import ParameterError

STEP = 8


@dataclass
class Chunk:
    start: int
    motion: object = None
    steps: list = field(default_factory=list)


class ReplayStream:
    def __init__(self, db, options=None, *, sample_rate: int):
        self.db, self.sample_rate, self.fps = db, int(sample_rate), float(db.fps)
        self.latency_s = STEP / self.fps
        self.n_samples = 0
        self.n_out = 0
        self.control = None
        self.words = []
        self.finished = False

    def set_control(self, control):
        self.control = control

    def push_words(self, words):
        self.words.extend(words)

    def push(self, samples) -> Chunk:
        x = np.asarray(samples)
        if x.dtype != np.float32 or x.ndim != 1 or not np.all(np.abs(x) <= 1):
            raise ParameterError(f"samples: expected float32 mono in [-1, 1]; got {x.dtype} {x.shape}")
        self.n_samples += x.shape[0]
        # a step of frames [t, t + STEP) is final once the audio reaches its end: frame t waits latency_s
        ready = int(self.n_samples / self.sample_rate * self.fps)
        return self._emit(ready - ready % STEP)

    def finish(self) -> Chunk:
        self.finished = True
        return self._emit(int(np.ceil(self.n_samples / self.sample_rate * self.fps)))

    def _emit(self, upto: int) -> Chunk:
        start = self.n_out
        if upto <= start:
            return Chunk(start)
        steps = []
        for t in range(start, upto, STEP):
            n = min(STEP, upto - t)
            g = t % (self.db.n_frames - STEP)
            steps.append({"step": t // STEP, "out_start": t, "out_end": t + n, "time_s": t / self.fps,
                          "recording": self.db.recordings[0].name, "source_start_s": g / self.fps,
                          "source_end_s": (g + n) / self.fps, "db_frame": g, "pose_rank": 1, "audio_rank": 2,
                          "pose_dist": 0.5, "audio_dist": float("nan"), "control": self.control, "keyword": None})
        frames = np.arange(start, upto) % (self.db.n_frames - STEP)
        self.n_out = upto
        return Chunk(start, self.db.motion_from_frames(frames), steps)
