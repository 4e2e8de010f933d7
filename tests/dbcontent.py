"""Comparing two database files dataset by dataset (builds that must agree: local, Dask, other CPUs)."""
from __future__ import annotations

import h5py
import numpy as np


def database_content(path) -> dict:
    """Every dataset's values by name, and the root attributes under ``"/attrs"``."""
    out = {}
    with h5py.File(path, "r") as h5:
        h5.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
        out["/attrs"] = {k: (v if not isinstance(v, np.ndarray) else v.tolist()) for k, v in h5.attrs.items()}
    return out


def differing(a_path, b_path) -> list[str]:
    """Names whose dtype, shape or values differ (bit for bit: -0.0 is not 0.0), or that only one file has."""
    a, b = database_content(a_path), database_content(b_path)
    out = sorted(set(a) ^ set(b))
    for k in sorted(set(a) & set(b)):
        x, y = a[k], b[k]
        if isinstance(x, np.ndarray):
            same = x.dtype == y.dtype and x.shape == y.shape and (
                x.tolist() == y.tolist() if x.dtype.kind == "O" else x.tobytes() == y.tobytes())
        else:
            same = x == y
        if not same:
            out.append(k)
    return out
