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
"""
from __future__ import annotations

import os
import signal
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from gesturedb.errors import GestureDBError, InputFileError, ParameterError
from gesturedb.io.atomic import atomic_open
from gesturedb.io.joints import leg_joints
from gesturedb.refiner.data import (STRIDE, WINDOW, TrainingData, cache_settings, database_identity, feature_identity,
                                    load_cache, make_training_data)
from gesturedb.refiner.model import Discriminator, Generator, gradient_penalty
from gesturedb.refiner.representation import from_channels_torch, to_channels_torch

FORMAT = 1


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
        for name in ("iterations", "batch", "n_critic", "width", "stride"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ParameterError(f"{name}: expected a positive integer, got {v!r}")
        if not (self.lr > 0):
            raise ParameterError(f"lr: expected a positive learning rate, got {self.lr!r}")
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
        with atomic_open(path, "wb") as f:
            torch.save(self.state(), f)

    def restore(self, ck: dict) -> None:
        self.G.load_state_dict(ck["generator"])
        self.D.load_state_dict(ck["discriminator"])
        self.opt_g.load_state_dict(ck["opt_g"])
        self.opt_d.load_state_dict(ck["opt_d"])
        self.iteration = int(ck["iteration"])
        self.history = [dict(zip(("iteration", "critic", "l1", "adv"), h)) for h in ck["history"]]
        self.gen.set_state(ck["sampler_state"])
        torch.set_rng_state(ck["torch_rng"])


def read_checkpoint(path) -> dict:
    """Load a checkpoint without executing code from it (``weights_only=True``)."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputFileError(path, "no such refiner checkpoint")
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many kinds for a damaged or foreign file
        raise InputFileError(path, f"expected a gesturedb refiner checkpoint, could not read it ({type(exc).__name__}: "
                                   f"{str(exc).splitlines()[0][:200]})") from None
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        raise InputFileError(path, f"format: expected a gesturedb refiner checkpoint of format {FORMAT}, "
                                   f"got {ck.get('format') if isinstance(ck, dict) else type(ck).__name__}")
    return ck


def check_compatible(ck: dict, db, path) -> None:
    """Refuse a checkpoint trained for another skeleton or feature configuration."""
    want = feature_identity(db)
    got = ck["features"]
    for key in ("joint_names", "parents", "fps", "audio_channels", "n_mfcc"):
        if got.get(key) != want[key]:
            what = {"joint_names": "skeleton joints", "parents": "skeleton hierarchy"}.get(key, key)
            a, b = got.get(key), want[key]
            if isinstance(a, list):
                a, b = f"{len(a)} entries", f"{len(b)} entries" if len(a) != len(b) else "different entries"
            raise InputFileError(path, f"{what}: the refiner was trained for {a}, database {db.path} has {b}; "
                                       "train a refiner on this database")


def train(db, out_path, *, config: TrainConfig | None = None, resume: bool = False, progress: bool = False,
          log=None, client=None, parts: int = 2, workers: int = 1) -> Trainer:
    """Train (or resume training) a refiner on a database and write its checkpoint.

    Parameters
    ----------
    db : gesturedb.db.database.Database
    out_path : path
        The checkpoint; the training windows' fakes are cached at ``out_path + ".data.h5"``.
    config : TrainConfig
    resume : bool
        Continue from ``out_path`` up to ``config.iterations`` iterations in all.
    client, parts, workers
        A Dask client: the training windows' self-search runs over ``parts`` shards on
        its workers, and their assembly too; without one the assembly runs on
        ``workers`` local processes (:func:`gesturedb.refiner.data.make_training_data`;
        the same data either way).
    """
    config = (config or TrainConfig()).check()
    out_path = os.fspath(out_path)
    folder = os.path.dirname(os.path.abspath(out_path))
    if not os.path.isdir(folder):
        raise ParameterError(f"output: folder {folder} does not exist")
    identity = database_identity(db)
    # a resumed run keeps its own settings, the seed and stride of its training data included
    ck = None
    if resume:
        ck = read_checkpoint(out_path)
        check_compatible(ck, db, out_path)
        if ck["identity"] != identity:
            raise InputFileError(out_path, f"identity: trained on another database than {db.path}; resume needs the same one")
        saved = dict(ck["config"])
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
            data = make_training_data(db, seed=config.seed, stride=config.stride, client=client, parts=parts,
                                      workers=workers, progress=report if progress else None, cache=cache)
        finally:
            for b in bars.values():
                b.close()
    tr = Trainer(data, config, identity, feature_identity(db))
    if ck is not None:
        tr.restore(ck)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=config.iterations, initial=tr.iteration, unit="it", desc="training", disable=None)
    last = time.monotonic()
    stop = {"now": False}

    def on_term(signum, frame):  # SIGTERM: finish the iteration, save, stop
        stop["now"] = True

    old = signal.signal(signal.SIGTERM, on_term) if _main_thread() else None
    try:
        while tr.iteration < config.iterations and not stop["now"]:
            rec = tr.step()
            if bar is not None:
                bar.update(1)
                bar.set_postfix(critic=f"{rec['critic']:.3f}", l1=f"{rec['l1']:.4f}", adv=f"{rec['adv']:.3f}")
            if time.monotonic() - last > config.checkpoint_every_s:
                tr.save(out_path)
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
    tr.save(out_path)
    return tr


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
        ck = read_checkpoint(path)
        if db is not None:
            check_compatible(ck, db, path)
        cfg = ck["config"]
        joints = ck["joints"].numpy()
        G = Generator(6 * len(joints), audio_channels=int(ck["features"]["audio_channels"]), width=int(cfg["width"]))
        G.load_state_dict(ck["generator"])
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
        from gesturedb.motion import Motion

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
