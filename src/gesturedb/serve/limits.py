"""What one client may ask of ``gesturedb serve``: sizes, lengths and times, with named defaults."""
from __future__ import annotations

from dataclasses import dataclass

from gesturedb.errors import ParameterError

#: The address the server binds unless told otherwise: this machine only.
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765


@dataclass(frozen=True)
class Limits:
    """Limits that keep one client from starving or crashing the others.

    Attributes
    ----------
    max_message_bytes : int
        Largest WebSocket message the app reads (1 MiB: 16 s of 16 kHz PCM16);
        larger ones end that stream with close code 1009. The WebSocket layer
        refuses messages over ``4 * max_message_bytes`` before they are buffered.
    max_upload_bytes : int
        Largest HTTP request body (a WAV for offline synthesis), 64 MiB: over
        half an hour of 16 kHz PCM16.
    max_audio_s : float
        Longest speech one stream or one upload may carry, seconds (20 minutes: a
        stream keeps its frames for the download, 18 MB at 15 fps and 55 joints).
    idle_s : float
        A stream that sends nothing for this long is closed (code 1008).
    max_streams : int
        WebSocket streams served at once; one more is told to try later (1013).
    max_errors : int
        Rejected messages (bad audio, unknown controls) a stream may send before it is closed.
    max_results : int
        Finished streams whose result stays downloadable (the oldest is dropped first).
    result_ttl_s : float
        How long a finished stream's result stays downloadable.
    max_source_s : float
        Longest database stretch ``GET /source`` returns.
    max_ahead_s : float
        How far a stream's audio may run ahead of real time (from its start): a client
        sending faster is slowed to real time after this much (its next message waits),
        so that one client feeding audio at full speed cannot take the CPU the others
        need for their steps. POST /synth is the way for a whole file at once.
    """

    max_message_bytes: int = 1 << 20
    max_upload_bytes: int = 64 << 20
    max_audio_s: float = 1200.0
    idle_s: float = 30.0
    max_streams: int = 64
    max_errors: int = 20
    max_results: int = 16
    result_ttl_s: float = 600.0
    max_source_s: float = 60.0
    max_ahead_s: float = 30.0

    def __post_init__(self):
        for name in ("max_message_bytes", "max_upload_bytes", "max_streams", "max_errors", "max_results"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ParameterError(f"Limits.{name}: expected a positive integer; got {v!r}")
        for name in ("max_audio_s", "idle_s", "result_ttl_s", "max_source_s", "max_ahead_s"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ParameterError(f"Limits.{name}: expected a positive number of seconds; got {v!r}")

    @property
    def ws_max_size(self) -> int:
        """What the WebSocket layer buffers at most: room above the app's limit so that a somewhat
        large message gets an error message from the app, and a huge one is refused unread."""
        return 4 * self.max_message_bytes
