"""`gesturedb serve DB.h5 [--host 127.0.0.1] [--port 8765]`: live gestures and the browser studio."""
from __future__ import annotations

import gesturedb
from gesturedb.cli._args import float_range, int_range
from gesturedb.errors import ParameterError


def add_parser(sub) -> None:
    from gesturedb.serve.limits import DEFAULT_HOST, DEFAULT_PORT, Limits

    d = Limits()
    p = sub.add_parser(
        "serve",
        help="serve live gestures (WebSocket), offline synthesis (HTTP) and the browser studio",
        description="Open the database once and serve it: the studio at http://HOST:PORT/, live streams at "
        "ws://HOST:PORT/stream, POST /synth for a WAV. The protocol is described in docs/live.md.",
    )
    p.add_argument("db", metavar="DB.h5")
    p.add_argument("--host", default=DEFAULT_HOST,
                   help="address to bind (default: %(default)s, this machine only; 0.0.0.0 opens it to the network)")
    p.add_argument("--port", type=int_range(0, 65535), default=DEFAULT_PORT, help="default: %(default)s")
    p.add_argument("--max-streams", type=int_range(1, 100000), default=d.max_streams,
                   help="live streams served at once (default: %(default)s)")
    p.add_argument("--idle", type=float_range(0.1, 86400), default=d.idle_s, dest="idle_s", metavar="S",
                   help="close a stream silent for this many seconds (default: %(default)g)")
    p.add_argument("--max-upload-mb", type=float_range(0.001, 65536), default=d.max_upload_bytes / 2**20,
                   help="largest POST /synth body, MiB (default: %(default)g)")
    p.add_argument("--workers", default="1", metavar="N",
                   help="serve from N processes, each applying its clients' steps (the apply is Python, one step "
                        "at a time per process); 'auto': the CPUs this process may use (default: %(default)s; "
                        "docs/live.md, 'Many streams')")
    p.add_argument("--no-batch", dest="batch_steps", action="store_false",
                   help="search each stream's steps alone instead of the waiting steps of all streams in one call "
                        "(the same frames; for comparison)")
    p.add_argument("--no-ahead", dest="ahead", action="store_false",
                   help="search each step only once its speech has come instead of pre-selecting it by pose "
                        "while its speech arrives (the same frames; for comparison; docs/live.md)")
    p.set_defaults(run=run)


def run(args) -> int:
    import logging

    from gesturedb.serve.limits import Limits

    try:
        import uvicorn  # noqa: F401 - the extra is there

        from gesturedb.serve import workers as W
        from gesturedb.serve.app import create_app
        from gesturedb.serve.websocket import uvicorn_options
    except ImportError as exc:
        raise ParameterError(f"serve needs the 'serve' extra: pip install 'gesturedb[serve]' ({exc})") from None
    n_workers = W.resolve_workers(args.workers)
    logging.basicConfig(level=logging.INFO, format="gesturedb serve: %(message)s")
    limits = Limits(max_streams=args.max_streams, idle_s=args.idle_s,
                    max_upload_bytes=int(args.max_upload_mb * 2**20))
    with gesturedb.open(args.db) as db:
        app = create_app(db, limits=limits, batch_steps=args.batch_steps, ahead=args.ahead)
        warm_s = app.state.gesturedb.warm_s  # create_app paid what the first stream would pay
        shown = f"[{args.host}]" if ":" in args.host else args.host
        print(f"gesturedb serve: {db.path} ({db.n_frames} frames at {db.fps:g} fps); studio at "
              f"http://{shown}:{args.port}/ , stream at ws://{shown}:{args.port}/stream (ready in {warm_s:.2f} s"
              + (f"; {n_workers} worker processes" if n_workers > 1 else "") + "; Ctrl-C stops)", flush=True)
        W.serve(app, args.host, args.port, n_workers, log_level="warning", **uvicorn_options(limits))
    return 0
