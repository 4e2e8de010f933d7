"""The WebSocket layer under the app: uvicorn's, with a lingering close and without permessage-deflate.

A message over ``Limits.ws_max_size`` is refused from its frame header, before it is
read (the server's memory stays put), and the connection fails with close code 1009.
uvicorn then closes the socket at once, with the rest of the message still unread
in the kernel, and Linux answers unread data at close with a TCP reset, which can
overtake the close frame: the client sees a dropped socket without a reason (issue
39 asks for the reason). 20 sends of 100 MB to ``gesturedb serve`` from a client
without compression: 5 saw no close code; with the server declining compression
as well, 10 of 20. So here the server sends the close frame and its end of the
stream, then keeps reading and dropping what the peer still sends until the peer
closes, for at most :data:`LINGER_S`, and only then closes the socket.

permessage-deflate is declined: every 40 ms audio message and every frames message
was compressed and decompressed on both ends (about a sixth of the event loop's
time at 16 clients), for PCM that barely compresses, on the loopback or a LAN
where bytes are cheap (docs/live.md, "Compression"; docs/live-measurements.md).

Reading pauses only when a message comes while another still waits for the app
(uvicorn pauses at every message and resumes at the app's every read: two epoll
calls and their bookkeeping per 40 ms audio message, for a client in real time
whose messages the app takes as they come). A client faster than the app is still
held back by TCP, one message later.
"""
from __future__ import annotations

from gesturedb.serve.limits import Limits

#: How long a connection whose peer broke the protocol (a message over the limit) keeps reading and
#: dropping what the peer still sends before closing: enough for 100 MB on the loopback (about 0.2 s);
#: a peer slower than that gets the reset after this, so one such peer holds a socket this long at most.
LINGER_S = 2.0

#: WebSocket keepalive: a silent peer is pinged after this many seconds and dropped if no pong comes in as many.
PING_S = 20.0

try:
    from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
except ImportError:  # an uvicorn before its Sans-I/O websockets layer: its own, closing at once
    WebSocketsSansIOProtocol = None


if WebSocketsSansIOProtocol is not None:
    class LingeringWebSocketProtocol(WebSocketsSansIOProtocol):
        """uvicorn's websockets (Sans-I/O) protocol whose failed connections linger before closing.

        Overrides three hooks of uvicorn 0.54's class: ``handle_parser_exception`` (websockets has
        failed the connection and queued its close frame: uvicorn writes it and closes the socket
        there), ``data_received`` (what comes after that is dropped unparsed) and
        ``send_receive_event_to_app`` (pauses reading only with a message already queued). All
        three, and the attributes used here, are as they were in 0.35, which brought the class; an
        uvicorn without it gets its default protocol (:func:`uvicorn_options`), which closes at once.
        """

        _lingering = False

        def data_received(self, data: bytes) -> None:
            if self._lingering:
                return  # the rest of a refused message: read so that the close sends no reset, never kept
            super().data_received(data)

        def send_receive_event_to_app(self) -> None:
            if self.read_paused or not self.queue.empty():
                super().send_receive_event_to_app()  # queues the message and pauses reading
                return
            # the app takes its messages as they come: queued without pausing (uvicorn pauses when it sees
            # read_paused False and resumes reading in receive() only when it is True)
            self.read_paused = True
            try:
                super().send_receive_event_to_app()
            finally:
                self.read_paused = False

        def handle_parser_exception(self) -> None:
            close = self.conn.close_sent
            self.queue.put_nowait({"type": "websocket.disconnect", "code": close.code, "reason": close.reason})
            self.transport.write(b"".join(self.conn.data_to_send()))
            self.close_sent = True
            if not self.transport.can_write_eof():  # TLS: no half-close; uvicorn's immediate close
                self.transport.close()
                return
            self._lingering = True
            # our end of the stream after the close frame: the peer, once it has read the frame, closes
            # its end, which closes the transport (``eof_received`` keeps nothing open)
            self.transport.write_eof()
            if self.read_paused:  # a message still with the app paused reading: the rest must drain
                self.read_paused = False
                self.transport.resume_reading()
            # uvicorn's close timer: cancelled when the connection is lost; while it is set, the app's
            # end does not close the transport either
            self.close_timer = self.loop.call_later(LINGER_S, self.transport.close)


def uvicorn_options(limits: Limits) -> dict:
    """``uvicorn.Config``'s WebSocket settings for ``gesturedb serve`` (the command and the tests' servers)."""
    return {
        "ws": "auto" if WebSocketsSansIOProtocol is None else LingeringWebSocketProtocol,
        "ws_max_size": limits.ws_max_size,
        "ws_per_message_deflate": False,
        "ws_ping_interval": PING_S,
        "ws_ping_timeout": PING_S,
    }
