"""WGAN-GP training of the refiner, checkpoints that resume exactly, and applying a trained refiner.

Loss (Habibie et al. 2022, Eq. 1-3): the critic D minimises
``D(fake) - D(real) + w3 * GP``; the generator G minimises
``w1 * L1(G_kNN, G(G_kNN)) - w2 * D(G(G_kNN))`` with ``w1, w2, w3 = 0.1, 1, 100``,
Adam at learning rate 1e-4. ``n_critic`` = 5 critic updates per generator
update, with Adam betas (0.5, 0.9): the WGAN-GP paper's settings, without which
the critic does not keep up and the generator's signal is noise (the gesture
paper does not give them).

Checkpoints hold everything a run needs to continue bit for bit: both models,
both optimisers, the iteration, the losses so far, the state of the batch
sampler's random generator, the database's identity and the feature
configuration. They are written to a temporary file and renamed, every
``checkpoint_every_s`` seconds and at the end, and on Ctrl-C. They load with
``torch.load(weights_only=True)``: no code from the file runs.

What is never written or read: a checkpoint with non-finite weights (a non-finite
loss stops training with an error before the next save, and :meth:`Trainer.save`
refuses non-finite weights); a checkpoint whose entries are missing, of the wrong
type, non-finite or out of bounds (:func:`read_checkpoint` checks every entry it
uses, and the settings against :data:`LIMITS`, before any model is built); a
training run that would replace a checkpoint without ``resume`` or ``overwrite``.
"""
from __future__ import annotations

import dataclasses
import os
import signal
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from gesturedb.errors import GestureDBError, InputFileError, ParameterError, echo, echo_list
from gesturedb.io.atomic import atomic_open
from gesturedb.io.joints import leg_joints
from gesturedb.motion import Motion
from gesturedb.refiner.data import (
    STRIDE,
    WINDOW,
    TrainingData,
    cache_settings,
    database_identity,
    feature_identity,
    load_cache,
    make_training_data,
)
from gesturedb.refiner.model import Discriminator, Generator, gradient_penalty
from gesturedb.refiner.representation import from_channels_torch, to_channels_torch
from gesturedb.threads import available_cpus

FORMAT = 1

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
    w1: float = 0.1
    w2: float = 1.0
    w3: float = 100.0
    width: int = 64  # 128 trains 1.5x slower on 2 CPU cores for no gain we could measure in minutes
    seed: int = 0
    checkpoint_every_s: float = 120.0
    # frames between training windows (the paper's 5): every frame is in window / stride
    # windows; a larger stride samples fewer windows, and the fakes' cache (83 kB a window)
    # and the self-search shrink with it, for databases far past the paper's 11 hours
    stride: int = STRIDE

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
        for name in ("w1", "w2", "w3"):
            v = getattr(self, name)
            if not (_is_real(v) and np.isfinite(v) and v >= 0):
                raise ParameterError(f"{name}: expected a finite loss weight >= 0, got {v!r}")
        if not (_is_int(self.seed) and 0 <= self.seed < 2**63 - 1):
            raise ParameterError(f"seed: expected an integer from 0 to {2**63 - 2}, got {self.seed!r}")
        if not (_is_real(self.checkpoint_every_s) and self.checkpoint_every_s >= 0):
            raise ParameterError(f"checkpoint_every_s: expected a number of seconds >= 0, got {self.checkpoint_every_s!r}")
        return self


@dataclass
class Trainer:
    """One training run over fixed training windows."""

    data: TrainingData
    config: TrainConfig
    identity: str
    features: dict
    G: Generator = field(init=False)
    D: Discriminator = field(init=False)
    iteration: int = 0
    history: list = field(default_factory=list)

    def __post_init__(self):
        self.config.check()
        torch.manual_seed(self.config.seed)
        C = self.data.channels
        A = self.data.audio_channels
        self.G = Generator(C, audio_channels=A, width=self.config.width)
        self.D = Discriminator(C, audio_channels=A, width=self.config.width)
        self.opt_g = torch.optim.Adam(self.G.parameters(), lr=self.config.lr, betas=tuple(self.config.betas))
        self.opt_d = torch.optim.Adam(self.D.parameters(), lr=self.config.lr, betas=tuple(self.config.betas))
        self.gen = torch.Generator().manual_seed(self.config.seed + 1)

    # -- one iteration ----------------------------------------------------------
    def _batch(self):
        W = self.data.n_windows
        i = torch.randint(0, W, (self.config.batch,), generator=self.gen).numpy()
        j = torch.randint(0, W, (self.config.batch,), generator=self.gen).numpy()  # real windows, independent of the fakes
        d = self.data  # sliced from the per-frame arrays and the fakes' memory map, batch by batch
        return tuple(torch.from_numpy(x) for x in (d.audio(i), d.fake(i), d.audio(j), d.real(j)))

    def critic_step(self) -> float:
        c = self.config
        a_f, knn, a_r, real = self._batch()
        with torch.no_grad():
            fake = self.G(a_f, knn)
        eps = torch.rand(c.batch, 1, 1, generator=self.gen)
        gp = gradient_penalty(self.D, a_r, real, a_f, fake, eps)
        loss = self.D(a_f, fake).mean() - self.D(a_r, real).mean() + c.w3 * gp
        self.opt_d.zero_grad()
        loss.backward()
        self.opt_d.step()
        return float(loss.detach())

    def generator_step(self) -> tuple[float, float]:
        c = self.config
        a_f, knn, _, _ = self._batch()
        out = self.G(a_f, knn)
        l1 = (out - knn).abs().mean()
        adv = -self.D(a_f, out).mean()
        loss = c.w1 * l1 + c.w2 * adv
        self.opt_g.zero_grad()
        loss.backward()
        self.opt_g.step()
        return float(l1.detach()), float(adv.detach())

    def step(self) -> dict:
        self.G.train()
        self.D.train()
        d = [self.critic_step() for _ in range(self.config.n_critic)]
        l1, adv = self.generator_step()
        self.iteration += 1
        rec = {"iteration": self.iteration, "critic": float(np.mean(d)), "l1": l1, "adv": adv}
        self.history.append(rec)
        return rec

    # -- checkpoints ------------------------------------------------------------
    def state(self) -> dict:
        cfg = dict(self.config.__dict__)
        cfg["betas"] = list(cfg["betas"])
        return {
            "format": FORMAT,
            "generator": self.G.state_dict(),
            "discriminator": self.D.state_dict(),
            "opt_g": self.opt_g.state_dict(),
            "opt_d": self.opt_d.state_dict(),
            "iteration": self.iteration,
            "history": [[h["iteration"], h["critic"], h["l1"], h["adv"]] for h in self.history],
            "sampler_state": self.gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            "config": cfg,
            "identity": self.identity,
            "features": self.features,
            "joints": torch.from_numpy(self.data.joints),
            "data": f"own windows ({WINDOW} frames, stride {self.config.stride}); fakes exclude the window's "
                    f"neighbourhood ({WINDOW} frames each side) in its own recording and its mirrored copy",
        }

    def save(self, path) -> None:
        """Write the checkpoint to a temporary sibling renamed over ``path`` once whole.

        Non-finite weights are refused (the previous checkpoint stays); a write the disk
        refuses is a one-line :class:`InputFileError` naming ``path`` (torch reported it as
        ``unexpected pos``)."""
        for name, model in (("generator", self.G), ("discriminator", self.D)):
            bad = _non_finite(model.state_dict())
            if bad:
                raise GestureDBError(f"{os.fspath(path)}: not saved: {name} {bad} after iteration {self.iteration}; "
                                     "the previous checkpoint (if any) is unchanged")
        state = self.state()
        with atomic_open(path, "wb") as f:
            out = _Recorded(f)
            try:
                torch.save(state, out)
            except Exception:
                if out.error is not None:
                    raise out.error from None  # atomic_open names the file and the system's reason
                raise

    def restore(self, ck: dict, path="checkpoint") -> None:
        """Continue from checkpoint ``ck`` (as :func:`read_checkpoint` returns it with ``training=True``)."""
        _load_state(self.G, ck["generator"], path, "generator")
        _load_state(self.D, ck["discriminator"], path, "discriminator")
        _load_state(self.opt_g, ck["opt_g"], path, "opt_g", self.G)
        _load_state(self.opt_d, ck["opt_d"], path, "opt_d", self.D)
        self.iteration = int(ck["iteration"])
        self.history = [dict(zip(("iteration", "critic", "l1", "adv"), h)) for h in ck["history"]]
        for field_, put in (("sampler_state", self.gen.set_state), ("torch_rng", torch.set_rng_state)):
            try:
                put(ck[field_])
            except (RuntimeError, TypeError, ValueError) as exc:
                raise InputFileError(path, f"{field_}: expected a saved random generator state, got one it "
                                           f"refused ({_first_line(exc)})") from None


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
    weights = ("generator", "discriminator") if training else ("generator",)
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
        if len(h) > ck["iteration"] or not all(isinstance(r, (list, tuple)) and len(r) == 4
                                               and all(_is_real(x) for x in r) for r in h):
            raise bad("history", f"expected at most {ck['iteration']} rows of 4 numbers")
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


def check_output(out_path, *, resume: bool, overwrite: bool) -> None:
    """Refuse to start a run over an existing file unless told to continue it or to replace it."""
    if resume and overwrite:
        raise ParameterError("resume, overwrite: expected at most one of them, got both")
    if not resume and not overwrite and os.path.lexists(out_path):
        raise InputFileError(out_path, "a file already exists here; continue its training with --resume, or start "
                                       "afresh over it with --overwrite")


def train(db, out_path, *, config: TrainConfig | None = None, resume: bool = False, overwrite: bool = False,
          progress: bool = False, log=None, scheduler=None, parts: int = 2, workers: int = 1,
          threads: int | None = None, client=None) -> Trainer:
    """Train (or resume training) a refiner on a database and write its checkpoint.

    Parameters
    ----------
    db : gesturedb.db.database.Database
    out_path : path
        The checkpoint; the training windows' fakes are cached at ``out_path + ".data.h5"``.
    config : TrainConfig
    resume : bool
        Continue from ``out_path`` up to ``config.iterations`` iterations in all.
    overwrite : bool
        Start afresh over an existing ``out_path`` (without it, or ``resume``, an existing
        file is refused: a trained checkpoint is never replaced by mistake).
    scheduler, parts, workers
        A Dask client (``client=`` is its older spelling, still accepted): the training
        windows' self-search runs over ``parts`` shards on
        its workers, and their assembly too; without one the assembly runs on
        ``workers`` local processes (:func:`gesturedb.refiner.data.make_training_data`;
        the same data either way).
    threads : int, optional
        torch's intra-op threads while training (restored afterwards); default
        :func:`gesturedb.threads.available_cpus`, not torch's own choice, which counts the
        machine's cores and ignores a CPU quota.
    """
    if client is not None:
        if scheduler is not None:
            raise ParameterError("train: expected scheduler= or its older spelling client=, not both")
        scheduler = client
    if threads is not None and (not _is_int(threads) or threads < 1):
        raise ParameterError(f"threads: expected a positive integer or None, got {threads!r}")
    config = (config or TrainConfig()).check()
    out_path = os.fspath(out_path)
    folder = os.path.dirname(os.path.abspath(out_path))
    if not os.path.isdir(folder):
        raise ParameterError(f"output: folder {folder} does not exist")
    check_output(out_path, resume=resume, overwrite=overwrite)
    identity = database_identity(db)
    # a resumed run keeps its own settings, the seed and stride of its training data included
    ck = None
    if resume:
        ck = read_checkpoint(out_path, training=True)
        check_compatible(ck, db, out_path)
        if ck["identity"] != identity:
            raise InputFileError(out_path, f"identity: trained on another database than {db.path}; resume needs the same one")
        saved = dict(ck["config"])
        if "betas" in saved:
            saved["betas"] = tuple(saved["betas"])
        saved.update(iterations=config.iterations, checkpoint_every_s=config.checkpoint_every_s)
        config = TrainConfig(**saved)
    cache = out_path + ".data.h5"
    settings = cache_settings(db, seed=config.seed, window=WINDOW, stride=config.stride)
    data = load_cache(cache, db, settings)
    if data is None:
        if log:
            log(f"searching the database for its own audio (training windows) -> {cache}")
        bars = {}

        def report(stage, done, total):
            if stage not in bars:
                from tqdm import tqdm

                for b in bars.values():
                    b.close()
                bars[stage] = tqdm(total=total, unit="win", desc=f"training data: {stage}", disable=None)
            bars[stage].update(done - bars[stage].n)

        try:
            data = make_training_data(db, seed=config.seed, stride=config.stride, scheduler=scheduler, parts=parts,
                                      workers=workers, progress=report if progress else None, cache=cache)
        finally:
            for b in bars.values():
                b.close()
    tr = Trainer(data, config, identity, feature_identity(db))
    if ck is not None:
        if tr.data.channels != 6 * len(ck["joints"]):
            raise InputFileError(out_path, f"joints: the checkpoint has {len(ck['joints'])} moving joints, the "
                                           f"training data {tr.data.channels // 6}")
        tr.restore(ck, out_path)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=config.iterations, initial=tr.iteration, unit="it", desc="training", disable=None)
    last = time.monotonic()
    saved_at = tr.iteration if ck is not None else None  # the iteration of the checkpoint on disk
    stop = {"now": False}

    def on_term(signum, frame):  # SIGTERM: finish the iteration, save, stop
        stop["now"] = True

    old = signal.signal(signal.SIGTERM, on_term) if _main_thread() else None
    # one thread per CPU this process may use: more would take turns on the same CPUs
    torch_threads = torch.get_num_threads()
    torch.set_num_threads(int(threads) if threads is not None else available_cpus())
    try:
        while tr.iteration < config.iterations and not stop["now"]:
            rec = tr.step()
            _check_losses(rec, out_path, saved_at)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(critic=f"{rec['critic']:.3f}", l1=f"{rec['l1']:.4f}", adv=f"{rec['adv']:.3f}")
            if time.monotonic() - last > config.checkpoint_every_s:
                tr.save(out_path)
                saved_at = tr.iteration
                last = time.monotonic()
    except KeyboardInterrupt:
        tr.save(out_path)
        if log:
            log(f"interrupted at iteration {tr.iteration}: checkpoint saved to {out_path} (continue with --resume)")
        raise
    finally:
        if bar is not None:
            bar.close()
        if old is not None:
            signal.signal(signal.SIGTERM, old)
        torch.set_num_threads(torch_threads)
    tr.save(out_path)
    return tr


def _check_losses(rec: dict, out_path: str, saved: int | None) -> None:
    """Stop a run whose loss is no longer finite, before it saves weights it has ruined."""
    for name in ("critic", "l1", "adv"):
        if not np.isfinite(rec[name]):
            kept = ("the checkpoint here is unchanged" if saved is None and os.path.exists(out_path)
                    else "nothing was saved" if saved is None else f"the checkpoint of iteration {saved} is kept")
            raise GestureDBError(f"{out_path}: training stopped at iteration {rec['iteration']}: {name} loss: expected "
                                 f"a finite value, got {rec[name]}; {kept}")


def _main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


class Refiner:
    """A trained generator that refines whole motions of any length in one pass.

    Use :meth:`refine` directly, or hand the object to
    ``Searcher.synthesize(..., refiner=...)``.
    """

    def __init__(self, G: Generator, joints: np.ndarray, features: dict, path: str | None = None):
        self.G = G.eval()
        self.joints = np.asarray(joints, dtype=np.int64)
        self.features = features
        self.path = path

    @classmethod
    def load(cls, path, db=None) -> "Refiner":
        ck = read_checkpoint(path)  # every entry used below is checked there, the width bounded
        if db is not None:
            check_compatible(ck, db, path)
        cfg = ck["config"]
        joints = ck["joints"].numpy()
        G = Generator(6 * len(joints), audio_channels=int(ck["features"]["audio_channels"]),
                      width=int(cfg.get("width", TrainConfig.width)))
        _load_state(G, ck["generator"], os.fspath(path), "generator")
        return cls(G, joints, ck["features"], os.fspath(path))

    def check(self, db) -> None:
        check_compatible({"features": self.features}, db, self.path or "refiner")

    def refine(self, motion, audio: np.ndarray):
        """Refine a motion given its speech features.

        Parameters
        ----------
        motion : gesturedb.motion.Motion
            T frames at the database fps on the database skeleton.
        audio : ndarray [shape=(T, 28)]
            Standardised audio features and their deltas, one row per frame.

        Returns
        -------
        gesturedb.motion.Motion
            Same skeleton, fps and root; refined local rotations of the moving joints
            above the hips (the legs keep the input's planted feet).
        """

        T = motion.rotations.shape[0]
        audio = np.asarray(audio, dtype=np.float32)
        if audio.shape != (T, int(self.features["audio_channels"])):
            raise ParameterError(f"audio: expected ({T}, {self.features['audio_channels']}) features for "
                                 f"{T} frames; got {audio.shape}")
        if list(motion.skeleton.names) != list(self.features["joint_names"]):
            raise GestureDBError(f"refiner {self.path}: motion skeleton has joints {len(motion.skeleton.names)}, "
                                 f"the refiner was trained for {len(self.features['joint_names'])}")
        x = to_channels_torch(motion.rotations, self.joints)
        a = torch.from_numpy(np.ascontiguousarray(audio.T[None]))
        with torch.no_grad():
            rot = from_channels_torch(self.G(a, x)[0], motion.rotations, self.joints)
        # the legs stay the k-NN's: assembly planted the feet with leg IK, and a refined
        # leg would slide them again (measured: skating 0.05 -> 0.18 m/s on held-out speech)
        legs = leg_joints(motion.skeleton.names, motion.skeleton.parents)
        rot[:, legs] = np.asarray(motion.rotations, dtype=np.float64)[:, legs]
        return Motion(skeleton=motion.skeleton, fps=motion.fps, rotations=rot, root_positions=motion.root_positions)
