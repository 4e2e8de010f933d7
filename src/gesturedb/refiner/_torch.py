"""torch, or a message that says how to install it (re-exported by :mod:`gesturedb.refiner`).

A module of its own so that modules of the package can use it without importing the package's
``__init__``, whose lazy import of :mod:`gesturedb.refiner.train` would close an import loop
(train -> validation -> autoencoder -> the package)."""
from __future__ import annotations

from gesturedb.errors import GestureDBError

INSTALL_HINT = "pip install 'gesturedb[refiner]' (or: pip install torch==2.13.0, the CPU build)"


def require_torch():
    """Import torch or raise a GestureDBError that says how to install it."""
    try:
        import torch
    except ImportError as exc:
        raise GestureDBError(f"the refiner needs PyTorch, which is not installed: {INSTALL_HINT}") from exc
    return torch
