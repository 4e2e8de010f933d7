"""The `gesturedb` command: a thin layer over the package, one module per command.

Every deliberate error (:class:`gesturedb.GestureDBError`) becomes one line on
stderr and exit status 2; anything else is a bug and keeps its traceback.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from gesturedb import __version__
from gesturedb.errors import GestureDBError

#: command name -> module in this package defining `add_parser(subparsers)` and `run(args)`
COMMANDS = {
    "build": "build",
    "info": "info",
    "export": "export",
    "synth": "synth",
    "keywords": "keywords",
    "masks": "masks",
    "eval": "eval",
    "render": "render",
    "retarget": "retarget",
    "refiner": "refiner",
    "graph": "graph",
    "upgrade": "upgrade",
    "shard": "shard",
    "serve": "serve",
}


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="gesturedb",
        description="Build gesture databases from speech + motion recordings and synthesize gestures by searching them.",
    )
    parser.add_argument("--version", action="version", version=f"gesturedb {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for _name, module in COMMANDS.items():
        importlib.import_module(f"gesturedb.cli.{module}").add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = make_parser()
    args = parser.parse_args(argv)
    _one_line_warnings(args.command)
    try:
        rc = int(args.run(args) or 0)
        sys.stdout.flush()  # inside the try: a closed pipe surfaces here, not at interpreter exit
        return rc
    except GestureDBError as exc:
        print(f"gesturedb {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"gesturedb {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # `gesturedb ... | head`: the reader left; stop quietly like any Unix tool. Point stdout at
        # devnull so the interpreter's final flush does not raise again.
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except RecursionError:
        # every parser has explicit limits; this is the backstop for one we missed
        print(f"gesturedb {args.command}: error: input nested too deeply to process (recursion limit)",
              file=sys.stderr)
        return 2
    except MemoryError:
        print(f"gesturedb {args.command}: error: out of memory (an input declares or needs more memory "
              "than this machine has)", file=sys.stderr)
        return 2


def _one_line_warnings(command: str) -> None:
    """Warnings as one line like errors (``gesturedb synth: warning: ...``), not a source excerpt."""
    import warnings

    def show(message, category, filename, lineno, file=None, line=None):
        kind = "" if category.__name__ in ("GestureDBWarning", "UserWarning") else f" ({category.__name__})"
        print(f"gesturedb {command}: warning{kind}: {message}", file=sys.stderr if file is None else file)

    warnings.showwarning = show


if __name__ == "__main__":
    sys.exit(main())
