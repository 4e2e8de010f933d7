"""The WebSocket layer's read pausing (gesturedb.serve.websocket), on uvicorn's protocol object itself."""
from __future__ import annotations

import asyncio

import pytest

pytest.importorskip("uvicorn")

from gesturedb.serve import websocket  # noqa: E402

pytestmark = pytest.mark.skipif(websocket.WebSocketsSansIOProtocol is None,
                                reason="an uvicorn without its Sans-I/O websockets protocol: its own is used")


class _Transport:
    def __init__(self):
        self.calls = []

    def pause_reading(self):
        self.calls.append("pause")

    def resume_reading(self):
        self.calls.append("resume")


def _protocol():
    """The protocol's state as uvicorn 0.54 keeps it once a connection is open (no socket)."""
    p = object.__new__(websocket.LingeringWebSocketProtocol)
    p.queue, p.transport, p.read_paused, p.close_sent = asyncio.Queue(), _Transport(), False, False
    return p


def _message(p, data: bytes):
    p.curr_msg_data_type, p.frames = "bytes", [data]
    p.send_receive_event_to_app()


def test_reading_pauses_only_when_a_message_waits_unread():
    """A client in real time (each message taken before the next comes) never pauses the socket; one
    faster than the app pauses it at its second unread message, and the app's reads resume it."""
    async def main():
        p = _protocol()
        for k in range(3):  # taken as they come
            _message(p, b"%d" % k)
            assert (await p.receive())["bytes"] == b"%d" % k
        assert p.transport.calls == [] and not p.read_paused
        _message(p, b"a")
        _message(p, b"b")  # a second message while the first waits: TCP holds the client back from here
        assert p.transport.calls == ["pause"] and p.read_paused
        _message(p, b"c")  # already paused: queued (the rest of one read from the socket), no second pause
        assert [(await p.receive())["bytes"] for _ in range(3)] == [b"a", b"b", b"c"]
        assert p.transport.calls == ["pause", "resume"] and not p.read_paused

    asyncio.run(main())
