"""Refiner settings and checkpoint files: what a run is configured with, and reading a checkpoint safely.

A checkpoint loads with ``torch.load(weights_only=True)``: no code from the file runs.
:func:`read_checkpoint` checks every entry it uses (presence, type, bounds, finite
values; the settings against :data:`LIMITS`) before any model is built from it, so a
damaged or crafted file is one :class:`~gesturedb.errors.InputFileError` naming the file
and the entry. Split from :mod:`gesturedb.refiner.train`, which writes them.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass

import numpy as np
import torch

from gesturedb.errors import InputFileError, ParameterError, echo, echo_list
from gesturedb.refiner.data import STRIDE, feature_identity

FORMAT = 1
#: the training recipe a checkpoint was made with: 1 before issue 40 (mean L1, no low-pass, no
#: augmentation, no validation), 2 now. A recipe-1 checkpoint applies as it was trained; it does not resume.
RECIPE = 2
#: the largest settings a run or a checkpoint may have, checked before any model is built
#: (a checkpoint saying width 30000 asked for 10.8 GB); far above anything trained here
LIMITS = {"iterations": 10**9, "batch": 4096, "n_critic": 100, "width": 1024, "stride": 10**6}
#: joints in a checkpoint's skeleton, and audio channels (the database's 28), at most
MAX_JOINTS = 1024
MAX_AUDIO_CHANNELS = 1024


def _is_int(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def _is_real(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)


def _first_line(exc: BaseException) -> str:
    """The first non-empty line of an exception's message, or its type (an empty message crashed the handler)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return f"{type(exc).__name__}: {lines[0][:200]}" if lines else type(exc).__name__


@dataclass
class TrainConfig:
    """Hyper-parameters (paper values where the paper gives them)."""

    iterations: int = 2000
    batch: int = 32
    lr: float = 1e-4
    betas: tuple = (0.5, 0.9)
    n_critic: int = 5
    w1: float = 0.01  # in gradient units (module docstring); docs/refiner.md says why 0.01
    w2: float = 1.0
    w3: float = 100.0
    width: int = 64  # 128 trains 1.5x slower on 2 CPU cores for no gain we could measure in minutes
    seed: int = 0
    checkpoint_every_s: float = 120.0
    # frames between training windows (the paper's 5): every frame is in window / stride
    # windows; a larger stride samples fewer windows, and the fakes' cache (83 kB a window)
    # and the self-search shrink with it, for databases far past the paper's 11 hours
    stride: int = STRIDE
    recipe: int = RECIPE
    #: the jitter penalty: its weight, and the cut-off (Hz) above which added energy is jitter
    w_hf: float = 1.0
    cutoff_hz: float = 3.0
    #: the band-power term's weight: the output keeps each joint's power per band (BAND_EDGES_HZ) of
    #: its input, two-sided (docs/refiner.md: the correction moved the database's speeds otherwise).
    #: 10: against a critic that knew its training windows, 1 let the 2-4 Hz arm band drift +10 %
    #: in 750 iterations, 10 held every band within 1 % for 500
    w_band: float = 10.0
    #: the posture term's weight, in gradient units as w1: the mean over a window of the correction,
    #: a posture offset, which moved the output away from the database's poses (FGD* vs DB +78 % on
    #: the input clips from the offset alone, docs/refiner.md) and which the band term leaves free
    w_pose: float = 1.0
    #: critic augmentation: crops of this fraction of a window, time warps of +-warp
    crop: float = 0.75
    warp: float = 0.1
    #: the last fraction of every recording (and its mirror) held back for validation, and how often
    val_fraction: float = 0.25
    val_every: int = 100

    def check(self) -> "TrainConfig":
        for name, hi in LIMITS.items():
            v = getattr(self, name)
            if not _is_int(v) or not 1 <= v <= hi:
                raise ParameterError(f"{name}: expected an integer from 1 to {hi}, got {v!r}")
        if not (_is_real(self.lr) and 0 < self.lr <= 1):
            raise ParameterError(f"lr: expected a learning rate in (0, 1], got {self.lr!r}")
        b = self.betas
        if not (isinstance(b, (tuple, list)) and len(b) == 2 and all(_is_real(x) and 0 <= x < 1 for x in b)):
            raise ParameterError(f"betas: expected two numbers in [0, 1), got {b!r}")
        for name in ("w1", "w2", "w3", "w_hf", "w_band", "w_pose"):
            v = getattr(self, name)
            if not (_is_real(v) and np.isfinite(v) and v >= 0):
                raise ParameterError(f"{name}: expected a finite loss weight >= 0, got {v!r}")
        if not (_is_int(self.seed) and 0 <= self.seed < 2**63 - 1):
            raise ParameterError(f"seed: expected an integer from 0 to {2**63 - 2}, got {self.seed!r}")
        if not (_is_real(self.checkpoint_every_s) and self.checkpoint_every_s >= 0):
            raise ParameterError(f"checkpoint_every_s: expected a number of seconds >= 0, got {self.checkpoint_every_s!r}")
        if not (_is_int(self.recipe) and self.recipe in (1, RECIPE)):
            raise ParameterError(f"recipe: expected 1 or {RECIPE}, got {self.recipe!r}")
        for name, lo, hi in (("cutoff_hz", 0, 1000), ("crop", 0, 1), ("warp", 0, 0.5), ("val_fraction", 0, 0.9)):
            v = getattr(self, name)
            if not (_is_real(v) and np.isfinite(v) and (lo < v <= hi if name == "crop" else lo <= v <= hi)):
                raise ParameterError(f"{name}: expected a number in {'(' if name == 'crop' else '['}{lo}, {hi}], "
                                     f"got {v!r}")
        if not (_is_int(self.val_every) and 1 <= self.val_every <= LIMITS["iterations"]):
            raise ParameterError(f"val_every: expected an integer from 1 to {LIMITS['iterations']}, got "
                                 f"{self.val_every!r}")
        return self


class _Recorded:
    """A binary file whose write errors are kept: torch.save turns them into ``unexpected pos``."""

    def __init__(self, f):
        self.f = f
        self.error: OSError | None = None

    def write(self, b) -> int:
        try:
            return self.f.write(b)
        except OSError as exc:
            self.error = exc
            raise

    def flush(self) -> None:
        self.f.flush()


def _plain(m: dict) -> dict:
    """Validation metrics as plain floats and lists (what ``torch.load(weights_only=True)`` reads back)."""
    return {k: [float(x) for x in v] if isinstance(v, (list, tuple, np.ndarray)) else float(v) for k, v in m.items()}


def _non_finite(tensors: dict) -> str | None:
    """``"<name>: expected finite values, got nan"`` for the first floating tensor with a non-finite value."""
    for name, t in tensors.items():
        if isinstance(t, torch.Tensor) and t.is_floating_point() and not bool(torch.isfinite(t).all()):
            v = t.detach().flatten()[~torch.isfinite(t.detach().flatten())][0].item()
            return f"{name}: expected finite values, got {v}"
    return None


def _load_state(target, state: dict, path, field_: str, model=None) -> None:
    """``target.load_state_dict(state)`` (a module, or an optimiser of ``model``), any refusal one line."""
    try:
        target.load_state_dict(state)
    except (RuntimeError, KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        text = " ".join(str(exc).split())[:300] or type(exc).__name__
        raise InputFileError(path, f"{field_}: does not fit the model of the checkpoint's settings ({text})") from None
    if model is not None:  # an optimiser: its moments must have the shapes of the parameters
        for p, st in target.state.items():
            for k, v in st.items():
                if isinstance(v, torch.Tensor) and k != "step" and v.shape != p.shape:
                    raise InputFileError(path, f"{field_}: state {k} has shape {tuple(v.shape)}, expected "
                                               f"{tuple(p.shape)} (the parameter's)")


#: what each entry of a checkpoint is; ``apply`` needs the first five, ``train --resume`` all
_ENTRIES = {"format": int, "generator": dict, "config": dict, "features": dict, "joints": torch.Tensor,
            "discriminator": dict, "opt_g": dict, "opt_d": dict, "iteration": int, "history": list,
            "sampler_state": torch.Tensor, "torch_rng": torch.Tensor, "identity": str}
_FOR_APPLY = ("format", "generator", "config", "features", "joints")


def read_checkpoint(path, *, training: bool = False) -> dict:
    """Load a checkpoint without executing code from it (``weights_only=True``) and check it.

    Every entry a refiner needs (``training``: also those a resumed run needs) is checked
    for presence, type, bounds (:data:`LIMITS`) and finite values before anything is built
    from it; any problem is one :class:`InputFileError` naming the file and the entry.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputFileError(path, "no such refiner checkpoint")
    _check_archive(path)
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many kinds for a damaged or foreign file
        raise InputFileError(path, f"expected a gesturedb refiner checkpoint, could not read it ({_first_line(exc)})") from None
    fmt = ck.get("format") if isinstance(ck, dict) else None
    if not (_is_int(fmt) and fmt == FORMAT):
        got = (repr(fmt) if _is_int(fmt) or fmt is None else type(fmt).__name__) if isinstance(ck, dict) \
            else type(ck).__name__
        raise InputFileError(path, f"format: expected a gesturedb refiner checkpoint of format {FORMAT}, got {got[:100]}")
    _check_entries(ck, path, training)
    return ck


def _check_archive(path: str) -> None:
    """A checkpoint is a zip archive (torch's format) whose members fit in the file: refused before
    torch reads it, so a header claiming terabytes allocates nothing."""
    import zipfile

    size = os.path.getsize(path)
    if size == 0:
        raise InputFileError(path, "expected a gesturedb refiner checkpoint, got an empty file (0 bytes)")
    try:
        with zipfile.ZipFile(path) as z:
            members = z.infolist()
    except Exception as exc:  # noqa: BLE001 - zipfile raises several kinds for a damaged archive
        raise InputFileError(path, f"expected a gesturedb refiner checkpoint (a torch zip archive), could not read "
                                   f"it ({_first_line(exc)})") from None
    for m in members:
        if m.compress_type != zipfile.ZIP_STORED or m.file_size > size:
            raise InputFileError(path, f"{m.filename[:100]}: expected an uncompressed member of at most the file's "
                                       f"{size} bytes, got {m.file_size} bytes (compression {m.compress_type})")


def _check_entries(ck: dict, path: str, training: bool) -> None:
    def bad(field_, problem):
        return InputFileError(path, f"{field_}: {problem}")

    for key in (_ENTRIES if training else _FOR_APPLY):
        if key not in ck:
            raise bad(key, "missing; expected a gesturedb refiner checkpoint with this entry")
        kind, v = _ENTRIES[key], ck[key]
        if not isinstance(v, kind) or (kind is int and isinstance(v, bool)):
            raise bad(key, f"expected {kind.__name__}, got {type(v).__name__}")
    # settings, before anything is sized from them
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    cfg = ck["config"]
    unknown = sorted(map(str, set(cfg) - known))
    if unknown:
        raise bad("config", f"expected settings among {sorted(known)}, got {unknown[0][:50]!r}")
    try:
        TrainConfig(**{k: tuple(v) if k == "betas" and isinstance(v, list) else v for k, v in cfg.items()}).check()
    except ParameterError as exc:
        raise bad("config", str(exc)) from None
    fe = ck["features"]
    names = fe.get("joint_names")
    if not (isinstance(names, list) and 1 <= len(names) <= MAX_JOINTS and all(isinstance(n, str) for n in names)):
        raise bad("features.joint_names", f"expected 1 to {MAX_JOINTS} joint names, got {type(names).__name__}")
    parents = fe.get("parents")
    if not (isinstance(parents, list) and len(parents) == len(names)
            and all(_is_int(q) and -1 <= q < len(names) for q in parents)):
        raise bad("features.parents", f"expected {len(names)} parent indices from -1 to {len(names) - 1}")
    if not (_is_real(fe.get("fps")) and np.isfinite(fe["fps"]) and 0 < fe["fps"] <= 1000):
        raise bad("features.fps", f"expected a frame rate in (0, 1000], got {fe.get('fps')!r:.50}")
    for key, hi in (("audio_channels", MAX_AUDIO_CHANNELS), ("n_mfcc", MAX_AUDIO_CHANNELS)):
        if not (_is_int(fe.get(key)) and 1 <= fe[key] <= hi):
            raise bad(f"features.{key}", f"expected an integer from 1 to {hi}, got {fe.get(key)!r:.50}")
    j = ck["joints"]
    if j.dtype != torch.int64 or j.ndim != 1 or not 1 <= j.numel() <= len(names):
        raise bad("joints", f"expected 1 to {len(names)} joint indices (int64, one axis), got {j.dtype} "
                            f"{tuple(j.shape)}")
    if not (bool((j[1:] > j[:-1]).all()) and 0 <= int(j[0]) and int(j[-1]) < len(names)):
        raise bad("joints", f"expected ascending joint indices from 0 to {len(names) - 1}, got "
                            f"{j[:8].tolist()}{'...' if j.numel() > 8 else ''}")
    _check_validation(ck, bad)
    weights = ("generator", "discriminator") if training else ("generator",)
    weights += ("best_generator",) if "best_generator" in ck else ()
    for key in weights:
        if not all(isinstance(k, str) and isinstance(t, torch.Tensor) for k, t in ck[key].items()):
            raise bad(key, "expected a state dict (names -> tensors)")
        problem = _non_finite(ck[key])
        if problem:
            raise bad(key, problem)
    if training:
        if not 0 <= ck["iteration"] <= LIMITS["iterations"]:
            raise bad("iteration", f"expected an integer from 0 to {LIMITS['iterations']}, got {ck['iteration']}")
        h = ck["history"]
        if len(h) > ck["iteration"] or not all(isinstance(r, (list, tuple)) and len(r) in (4, 5)
                                               and all(_is_real(x) for x in r) for r in h):
            raise bad("history", f"expected at most {ck['iteration']} rows of 4 or 5 numbers")
        for key in ("opt_g", "opt_d"):
            st = ck[key].get("state")
            tensors = {f"state {k} {n}": t for k, d in (st.items() if isinstance(st, dict) else ())
                       if isinstance(d, dict) for n, t in d.items()}
            problem = _non_finite(tensors)
            if problem:
                raise bad(key, problem)
        for key in ("sampler_state", "torch_rng"):
            if ck[key].dtype != torch.uint8 or ck[key].ndim != 1:
                raise bad(key, f"expected a random generator state (uint8, one axis), got {ck[key].dtype} "
                               f"{tuple(ck[key].shape)}")


def _check_validation(ck: dict, bad) -> None:
    """The optional ``validation`` entry: the verdict and the best iteration a refiner is judged and applied by."""
    if "best_generator" in ck and not isinstance(ck["best_generator"], dict):
        raise bad("best_generator", f"expected dict, got {type(ck['best_generator']).__name__}")
    val = ck.get("validation")
    if val is None:
        if "best_generator" in ck:
            raise bad("validation", "missing; expected the validation that chose best_generator")
        return
    if not isinstance(val, dict) or not isinstance(val.get("log"), list):
        raise bad("validation", "expected a dict with a log of validation rows")
    v = val.get("verdict")
    if v is not None and not (isinstance(v, dict) and isinstance(v.get("beats_identity"), bool)
                              and all(_is_real(v.get(k)) for k in ("identity_score", "best_score", "improvement"))
                              and _is_int(v.get("best_iteration"))):
        raise bad("validation.verdict", "expected beats_identity (bool), identity_score, best_score, improvement "
                                        "(numbers) and best_iteration (int)")
    if v is not None and "guards" in v and not (isinstance(v["guards"], list)
                                                and all(isinstance(g, str) for g in v["guards"])):
        raise bad("validation.verdict.guards", f"expected a list of guard names, got {echo(v['guards'])}")
    if v is not None and "best_generator" not in ck:
        raise bad("best_generator", "missing; the validation verdict names a best iteration, whose weights it holds")
    t = val.get("trained_best")
    if t is not None and not (isinstance(t, dict) and _is_int(t.get("iteration")) and isinstance(t.get("metrics"), dict)
                              and all(_is_real(t["metrics"].get(k)) for k in ("score", "jerk"))):
        raise bad("validation.trained_best", "expected None or an iteration (int) and its metrics (score, jerk, ...)")


def check_compatible(ck: dict, db, path) -> None:
    """Refuse a checkpoint trained for another skeleton or feature configuration."""
    want = feature_identity(db)
    got = ck["features"]
    for key in ("joint_names", "parents", "fps", "audio_channels", "n_mfcc"):
        if got.get(key) != want[key]:
            what = {"joint_names": "skeleton joints", "parents": "skeleton hierarchy"}.get(key, key)
            a, b = got.get(key), want[key]
            if isinstance(a, list) and isinstance(b, list):
                raise InputFileError(path, f"{what}: the refiner was trained for {len(a)} entries, database {db.path} "
                                           f"has {len(b)}; {_list_difference(a, b)}; train a refiner on this database")
            raise InputFileError(path, f"{what}: the refiner was trained for {echo(a)}, database {db.path} has "
                                       f"{echo(b)}; train a refiner on this database")


def _list_difference(trained: list, database: list) -> str:
    """Which entries of two lists differ, for a message: by position, then what only one side has.

    ``1 of the first 55 differ: entry 3: 'LeftHand' (refiner) vs 'L_Hand' (database); only in the
    database: entry 55 'Jaw'``;
    `echo_list` names the first `MAX_ECHO_ITEMS` of each kind and counts the rest.
    """
    n = min(len(trained), len(database))
    changed = [f"entry {i}: {echo(trained[i])} (refiner) vs {echo(database[i])} (database)"
               for i in range(n) if trained[i] != database[i]]
    parts = [f"{len(changed)} of the first {n} differ: {echo_list(changed)}"] if changed else []
    for side, longer in (("the refiner", trained), ("the database", database)):
        if len(longer) > n:
            extra = [f"entry {i} {echo(longer[i])}" for i in range(n, len(longer))]
            parts.append(f"only in {side}: {echo_list(extra)}")
    return "; ".join(parts) or "same entries"
