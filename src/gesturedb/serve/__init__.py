"""``gesturedb serve``: live gestures over a WebSocket, offline synthesis over HTTP, a browser studio.

=================  ==========================================================
``app``            :func:`create_app`: the Starlette ASGI app over one open database
``session``        one WebSocket stream: audio and controls in, frames out
``protocol``       the wire format (binary frames layout, audio formats, close codes)
``limits``         :class:`Limits`: message size, upload length, idle time, streams
``websocket``      uvicorn's WebSocket settings; a refused message's close that lingers
``client``         :class:`~gesturedb.serve.client.LiveClient`: a small client for engines
``vendor``         three.js from Debian's libjs-three, found at run time
``studio/``        the browser studio's page, script and audio worklet
=================  ==========================================================

Needs the ``serve`` extra (``pip install gesturedb[serve]``). The protocol is
described in ``docs/live.md``.
"""
from __future__ import annotations

from gesturedb.serve.limits import DEFAULT_HOST, DEFAULT_PORT, Limits

__all__ = ["DEFAULT_HOST", "DEFAULT_PORT", "Limits", "create_app"]


def create_app(db, **kwargs):
    """The ASGI app; see :func:`gesturedb.serve.app.create_app` (imported here lazily: the client needs no Starlette)."""
    # local on purpose: serve.app imports Starlette at its top, which the client and `--help` do not need
    from gesturedb.serve.app import create_app as _create

    return _create(db, **kwargs)
