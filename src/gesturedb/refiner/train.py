"""WGAN-GP training of the refiner, validation, checkpoints that resume exactly, and applying it.

Loss (Habibie et al. 2022, Eq. 1-3): the critic D minimises
``D(fake) - D(real) + w3 * GP``; the generator G minimises
``w1 * L1(G_kNN, G(G_kNN)) - w2 * D(G(G_kNN))``, Adam at learning rate 1e-4.
``n_critic`` = 5 critic updates per generator update, with Adam betas (0.5, 0.9):
the WGAN-GP paper's settings (the gesture paper does not give them).

The recipe (``recipe`` 2; docs/refiner.md gives what each part changed, measured):

- **L1 in gradient units.** The L1 term is summed over a window's channels and frames
  and divided by ``sqrt(channels x frames)``: its gradient at the generator's output
  then has norm 1 per window (when the correction is non-zero everywhere), the norm
  the gradient penalty holds the critic's gradient at. ``w1`` is the ratio of the two
  pulls: 1 = equal. The paper's mean over 20,736 elements made the adversarial
  gradient about 1,000x the ``0.1 * L1`` one; the ratio is logged (``ratio``).
- **No added jitter**: ``w_hf`` times the energy the output adds above ``cutoff_hz``
  (3 Hz) over the input's, relative to the input's (:func:`model.high_band_energy`;
  one-sided: removing high frequencies, smoothing a seam, costs nothing). The
  critic's input gradient is broadband, and corrections that followed it doubled the
  jerk held out. Gesture strokes carry their power below 3 Hz at any frame rate.
- **Frozen legs** (:class:`model.Generator`): refining puts them back as they were.
- **Critic augmentation**: crops and time warps (:func:`model.augment`) of reals and
  fakes alike, in the critic's and the generator's steps.
- **Reals and fakes processed alike**: fakes are assembled as synthesis assembles
  them; the same assembly of a real (contiguous) window changes only the legs (foot
  IK; the upper body within 1e-15), so the critic sees no leg channel.
- **Band power and posture kept**: ``w_band`` times :func:`model.band_change` (each
  joint's power per band, two-sided) and ``w_pose`` times the correction's window
  mean (in the L1 term's gradient units): the first recipe's output moved away from
  the database by a posture offset and a narrower speed distribution.
- **Validation** (:mod:`gesturedb.refiner.validation`): every ``val_every``
  iterations the generator refines the held-back windows; the identity (iteration 0)
  is kept unless a generator the verdict endorses (every guard kept, the score 2 %
  lower) comes, then the lowest score among those; beside the last generator (the
  last resumes, the kept one is applied), with the verdict against the identity.

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

import os
import signal
import sys
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from gesturedb.errors import GestureDBError, InputFileError, ParameterError
from gesturedb.io.atomic import atomic_open
from gesturedb.io.joints import leg_joints
from gesturedb.motion import Motion
from gesturedb.refiner.checkpoint import (
    FORMAT,
    LIMITS,
    RECIPE,
    TrainConfig,
    _first_line,
    _is_int,
    _load_state,
    _non_finite,
    _plain,
    _Recorded,
    check_compatible,
    read_checkpoint,
)
from gesturedb.refiner.data import (
    WINDOW,
    TrainingData,
    cache_settings,
    database_identity,
    feature_identity,
    load_cache,
    make_training_data,
)
from gesturedb.refiner.model import Discriminator, Generator, augment, band_change, gradient_penalty, high_band_energy
from gesturedb.refiner.representation import from_channels_torch, to_channels_torch
from gesturedb.refiner.validation import (
    GUARDS,
    Validator,
    describe_worse,
    format_metrics,
    guard_values,
    missing_guards,
    verdict,
    worse_guards,
)
from gesturedb.threads import available_cpus

__all__ = ["FORMAT", "LIMITS", "RECIPE", "Refiner", "TrainConfig", "Trainer", "check_output", "read_checkpoint",
           "resolve_device", "train"]
DEVICES = ("auto", "cpu", "cuda")
#: seconds between progress lines while the progress bar is off (stderr is not a terminal: a log file,
#: a batch job), so a log shows the losses more often than every validation (minutes on a CPU)
LOG_EVERY_S = 60.0


def resolve_device(device: str) -> str:
    """``"auto"`` -> ``"cuda"`` when torch sees a GPU, else ``"cpu"``; ``"cuda"`` without one is refused."""
    if device not in DEVICES:
        raise ParameterError(f"device: expected one of {', '.join(DEVICES)}, got {device!r}")
    has = torch.cuda.is_available()
    if device == "cuda" and not has:
        raise ParameterError("device: cuda asked for, but torch sees no CUDA GPU (torch "
                             f"{torch.__version__}; the default install is the CPU build); use --device cpu or auto")
    return "cuda" if device == "cuda" or (device == "auto" and has) else "cpu"

def make_generator(cfg: dict, features: dict, joints, channels: int, audio_channels: int) -> Generator:
    """The generator of a run's settings: recipe 2 freezes the legs."""
    width = int(cfg.get("width", TrainConfig.width))
    if int(cfg.get("recipe", 1)) < 2:
        return Generator(channels, audio_channels=audio_channels, width=width)
    return Generator(channels, audio_channels=audio_channels, width=width, frozen=frozen_channels(features, joints))


def jitter_cutoff_hz(config: "TrainConfig", fps: float) -> float | None:
    """The jitter penalty's cut-off, or None when it lies at or past the Nyquist frequency (or is 0)."""
    c = float(config.cutoff_hz)
    return c if 0 < c < float(fps) / 2 else None


def frozen_channels(features: dict, joints) -> np.ndarray:
    """(k,) int64: the gesture channels of leg joints (6 per joint), which refining puts back as they were."""
    names, parents = features.get("joint_names") or [], features.get("parents") or []
    legs = set(int(j) for j in leg_joints(names, parents)) if len(names) == len(parents) and names else set()
    pos = [i for i, j in enumerate(np.asarray(joints).tolist()) if j in legs]
    return (6 * np.asarray(pos, dtype=np.int64)[:, None] + np.arange(6)).ravel()


@dataclass
class Trainer:
    """One training run over fixed training windows, on ``device`` ("cpu" or "cuda").

    ``validator`` (:class:`gesturedb.refiner.validation.Validator`, optional) measures the
    generator on the validation windows; :meth:`validate` keeps the best generator.
    """

    data: TrainingData
    config: TrainConfig
    identity: str
    features: dict
    device: str = "cpu"
    validator: Validator | None = None
    G: Generator = field(init=False)
    D: Discriminator = field(init=False)
    iteration: int = 0
    #: the checkpoint's iteration when this run resumed it (0: a new run)
    resumed_from: int = 0
    history: list = field(default_factory=list)

    def __post_init__(self):
        self.config.check()
        if self.config.recipe != RECIPE:
            raise ParameterError(f"recipe: a run trains with recipe {RECIPE}, got {self.config.recipe}")
        torch.manual_seed(self.config.seed)
        C = self.data.channels
        A = self.data.audio_channels
        cfg = dict(self.config.__dict__)
        self.dev = torch.device(self.device)
        self.G = make_generator(cfg, self.features, self.data.joints, C, A).to(self.dev)
        frozen = set(frozen_channels(self.features, self.data.joints).tolist())
        free = [c for c in range(C) if c not in frozen]
        self.free = torch.tensor(free, dtype=torch.long, device=self.dev)
        self.fps = float(self.features.get("fps", 0) or 0)
        self.cutoff_hz = jitter_cutoff_hz(self.config, self.fps)
        self.D = Discriminator(len(free), audio_channels=A, width=self.config.width).to(self.dev)
        # the untrained generator is the identity (its last layer is zero): validation's first candidate
        self._identity_state = {k: t.detach().cpu().clone() for k, t in self.G.state_dict().items()}
        self.opt_g = torch.optim.Adam(self.G.parameters(), lr=self.config.lr, betas=tuple(self.config.betas))
        self.opt_d = torch.optim.Adam(self.D.parameters(), lr=self.config.lr, betas=tuple(self.config.betas))
        self.gen = torch.Generator().manual_seed(self.config.seed + 1)  # CPU: the same draws on any device
        self.train_idx = self.data.train_windows
        if self.train_idx.size == 0:
            raise ParameterError("training data: expected at least one training window, got none")
        # [iteration, score, jerk, band..., hellinger, critic_gap, hf, hellinger_db, band_db, fgd_db]
        self.val_log: list = []
        self.best: dict | None = None  # {"iteration", "metrics", "generator" (CPU state dict)}; iteration 0: the identity
        self.trained_best: dict | None = None  # {"iteration", "metrics"}: the best trained generator, kept or not
        self.remeasured: int | None = None  # the best's iteration, when restore() had to measure it again

    # -- one iteration ----------------------------------------------------------
    def _batch(self):
        n = len(self.train_idx)
        i = self.train_idx[torch.randint(0, n, (self.config.batch,), generator=self.gen).numpy()]
        j = self.train_idx[torch.randint(0, n, (self.config.batch,), generator=self.gen).numpy()]  # independent reals
        d = self.data  # sliced from the per-frame arrays and the fakes' memory map, batch by batch
        return tuple(torch.from_numpy(x).to(self.dev) for x in (d.audio(i), d.fake(i), d.audio(j), d.real(j)))

    def _critic_view(self, audio, gesture):
        """What the critic sees of a batch: the free channels, cropped and warped."""
        c = self.config
        return augment(audio, gesture.index_select(1, self.free), self.gen, crop=c.crop, warp=c.warp)

    def critic_step(self) -> float:
        c = self.config
        a_f, knn, a_r, real = self._batch()
        with torch.no_grad():
            fake = self.G(a_f, knn)
        a_f, fake = self._critic_view(a_f, fake)
        a_r, real = self._critic_view(a_r, real)
        eps = torch.rand(c.batch, 1, 1, generator=self.gen).to(self.dev)
        gp = gradient_penalty(self.D, a_r, real, a_f, fake, eps)
        loss = self.D(a_f, fake).mean() - self.D(a_r, real).mean() + c.w3 * gp
        self.opt_d.zero_grad()
        loss.backward()
        self.opt_d.step()
        return float(loss.detach())

    def generator_step(self) -> tuple[float, float, float]:
        """One generator update; returns (L1 in gradient units, adversarial loss, gradient ratio).

        The ratio is ``|| d(w2 adv + jitter)/d out || / || d(w1 L1)/d out ||`` at the generator's
        output (NaN while the correction is zero everywhere, where L1 has no gradient)."""
        c = self.config
        a_f, knn, _, _ = self._batch()
        out = self.G(a_f, knn)
        corr = (out - knn).detach().index_select(1, self.free)
        n = corr.shape[1] * corr.shape[2]
        l1 = corr.abs().sum(dim=(1, 2)).mean() / n ** 0.5
        adv = -self.D(*self._critic_view(a_f, out)).mean()
        loss = c.w2 * adv
        if self.cutoff_hz is not None and c.w_hf > 0:
            e_out = high_band_energy(out.index_select(1, self.free), self.fps, self.cutoff_hz).sum(1)
            e_in = high_band_energy(knn.index_select(1, self.free), self.fps, self.cutoff_hz).sum(1)
            loss = loss + c.w_hf * (torch.relu(e_out - e_in) / (e_in + 1e-8)).mean()
        if c.w_band > 0 and self.fps > 0:
            loss = loss + c.w_band * band_change(out.index_select(1, self.free), knn.index_select(1, self.free),
                                                 self.fps)
        if c.w_pose > 0:
            # |window mean of the correction|, summed over channels and scaled so that its gradient at the
            # output has norm 1 per window when every channel's mean is non-zero (sqrt(C / T): each of the
            # C T elements gets 1/T), the L1 term's gradient units: w_pose is its pull against the critic's
            pose = (out - knn).index_select(1, self.free).mean(-1)
            loss = loss + c.w_pose * (pose.abs().sum(1) / (pose.shape[1] / out.shape[-1]) ** 0.5).mean()
        g_adv, = torch.autograd.grad(loss, out)
        g_l1 = torch.zeros_like(out)
        g_l1[:, self.free] = c.w1 * torch.sign(corr) / (n ** 0.5 * out.shape[0])
        self.opt_g.zero_grad()
        out.backward(g_adv + g_l1)
        self.opt_g.step()
        norm_l1 = float(g_l1.norm())
        ratio = float(g_adv.norm()) / norm_l1 if norm_l1 > 0 else float("nan")
        return float(l1), float(adv.detach()), ratio

    def step(self) -> dict:
        self.G.train()
        self.D.train()
        d = [self.critic_step() for _ in range(self.config.n_critic)]
        l1, adv, ratio = self.generator_step()
        self.iteration += 1
        rec = {"iteration": self.iteration, "critic": float(np.mean(d)), "l1": l1, "adv": adv, "ratio": ratio}
        self.history.append(rec)
        return rec

    # -- validation -------------------------------------------------------------
    def validate(self) -> dict | None:
        """Refine the validation windows with the generator of now; log the metrics and keep the
        generator if it is the best so far. None without a validator."""
        v = self.validator
        if v is None:
            return None
        m = self._measure(self.G)
        self.val_log.append([self.iteration, m["score"], m["jerk"], *m["band"], m["hellinger"], m["critic_gap"],
                             m["hf"], m.get("hellinger_db", float("nan")), m.get("band_db", float("nan")),
                             m.get("fgd_db", float("nan"))])
        if self.best is None:
            # the identity is the first candidate (the untrained generator: its last layer is zero, it adds
            # nothing), so a trained generator is kept only when the verdict would endorse it; otherwise the
            # checkpoint applies the identity and says so
            self.best = {"iteration": 0, "metrics": m if self.iteration == 0 else v.identity,
                         "generator": self._identity_state}
        if self.iteration > 0:
            if self._better(m, self.trained_best):
                self.trained_best = {"iteration": self.iteration, "metrics": m}
            if self._endorsed(m) and (self.best["iteration"] == 0 or m["score"] < self.best["metrics"]["score"]):
                self.best = {"iteration": self.iteration, "metrics": m,
                             "generator": {k: t.detach().cpu().clone() for k, t in self.G.state_dict().items()}}
        return m

    def _endorsed(self, m: dict) -> bool:
        """Whether the verdict would call a generator with validation metrics ``m`` better than the identity."""
        ident = self.validator.identity
        return verdict(ident["score"], m["score"], 1, identity=ident, best=m)["beats_identity"]

    def _measure(self, G: Generator) -> dict:
        """Validation metrics of generator ``G`` on the validation windows, the critic gap by the critic of now."""
        v = self.validator
        G.eval()
        with torch.no_grad():
            a = torch.from_numpy(v.audio).to(self.dev)
            out = G(a, torch.from_numpy(v.knn).to(self.dev))
            real = torch.from_numpy(v.real).to(self.dev).index_select(1, self.free)
            gap = float(self.D(a, real).mean() - self.D(a, out.index_select(1, self.free)).mean())
        return v.measure(out.cpu().numpy(), critic_gap=gap)

    def _better(self, m: dict, kept: dict | None) -> bool:
        """Whether validation metrics ``m`` make a better trained candidate than ``kept`` ({"metrics": ...}
        or None): one that keeps every guard (:data:`gesturedb.refiner.validation.GUARDS`) beats one that
        does not, then the lower score wins. The closest trained generator, which the verdict reports
        when the identity is kept."""
        if kept is None:
            return True
        ident = self.validator.identity
        keeps, was = not worse_guards(ident, m), not worse_guards(ident, kept["metrics"])
        return keeps > was or (keeps == was and m["score"] < kept["metrics"]["score"])

    def verdict(self) -> dict | None:
        """The verdict so far (:func:`gesturedb.refiner.validation.verdict`), None before any validation.

        When the kept generator is the identity (no trained one the verdict would endorse),
        ``identity_kept`` is True and ``trained`` gives the best trained generator's iteration, score
        gain and the guards it made worse (by the same rule), so a reader sees why none was kept."""
        if self.validator is None or self.best is None:
            return None
        ident = self.validator.identity
        v = verdict(ident["score"], self.best["metrics"]["score"], self.best["iteration"], identity=ident,
                    best=self.best["metrics"])
        if self.best["iteration"] == 0:
            v["identity_kept"] = True
            t = self.trained_best
            if t is not None:
                tv = verdict(ident["score"], t["metrics"]["score"], t["iteration"], identity=ident, best=t["metrics"])
                v["trained"] = {"iteration": tv["best_iteration"], "improvement": tv["improvement"],
                                "worse": tv["worse"]}
        return v

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
            "history": [[h["iteration"], h["critic"], h["l1"], h["adv"], h.get("ratio", float("nan"))]
                        for h in self.history],
            "sampler_state": self.gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            "config": cfg,
            "identity": self.identity,
            "features": self.features,
            "joints": torch.from_numpy(self.data.joints),
            "data": f"own windows ({WINDOW} frames, stride {self.config.stride}); fakes exclude the window's "
                    f"neighbourhood ({WINDOW} frames each side) in its own recording and its mirrored copy",
            **self._validation_state(),
        }

    def _validation_state(self) -> dict:
        if self.validator is None:
            return {}
        v = self.validator
        out = {"validation": {
            "fraction": float(self.config.val_fraction), "every": int(self.config.val_every),
            "windows": int(v.n), "train_windows": int(len(self.train_idx)),
            "capture_jerk_m_s3": float(v.capture["jerk"]), "identity": _plain(v.identity),
            "log": [[float(x) for x in row] for row in self.val_log],
            "best": None if self.best is None else {"iteration": int(self.best["iteration"]),
                                                    "metrics": _plain(self.best["metrics"])},
            "trained_best": None if self.trained_best is None else {
                "iteration": int(self.trained_best["iteration"]), "metrics": _plain(self.trained_best["metrics"])},
            "verdict": self.verdict(),
        }}
        if self.best is not None:
            out["best_generator"] = self.best["generator"]
        return out

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
        self.history = [dict(zip(("iteration", "critic", "l1", "adv", "ratio"), h)) for h in ck["history"]]
        val = ck.get("validation")
        if val is not None and self.validator is not None:
            self.val_log = [list(r) for r in val["log"]]
            if val.get("best") is not None and "best_generator" in ck:
                self.best = {"iteration": int(val["best"]["iteration"]), "metrics": dict(val["best"]["metrics"]),
                             "generator": ck["best_generator"]}
                if set(GUARDS) - set(guard_values(self.best["metrics"])):
                    # kept before the verdict's guards existed: the metrics they need were never measured,
                    # and a verdict from the rest would call better what the guards may not. Measured
                    # again here, before the RNG states are restored below (building a generator draws
                    # from torch's RNG), so the resumed run stays bit for bit the uninterrupted one
                    G = make_generator(dict(self.config.__dict__), self.features, self.data.joints,
                                       self.data.channels, self.data.audio_channels).to(self.dev)
                    _load_state(G, ck["best_generator"], path, "best_generator")
                    self.best["metrics"] = self._measure(G)
                    self.remeasured = self.best["iteration"]
            t = val.get("trained_best")
            if t is not None:
                self.trained_best = {"iteration": int(t["iteration"]), "metrics": dict(t["metrics"])}
            elif self.best is not None and self.best["iteration"] > 0:
                self.trained_best = {"iteration": self.best["iteration"], "metrics": self.best["metrics"]}
            if self.best is not None and self.best["iteration"] > 0 and not self._endorsed(self.best["metrics"]):
                # kept before the identity was a candidate, and not better than it (a guard worse, or a
                # score less than the margin lower): the identity is kept instead
                self.best = {"iteration": 0, "metrics": self.validator.identity, "generator": self._identity_state}
        for field_, put in (("sampler_state", self.gen.set_state), ("torch_rng", torch.set_rng_state)):
            try:
                put(ck[field_])
            except (RuntimeError, TypeError, ValueError) as exc:
                raise InputFileError(path, f"{field_}: expected a saved random generator state, got one it "
                                           f"refused ({_first_line(exc)})") from None


def check_output(out_path, *, resume: bool, overwrite: bool) -> None:
    """Refuse to start a run over an existing file unless told to continue it or to replace it."""
    if resume and overwrite:
        raise ParameterError("resume, overwrite: expected at most one of them, got both")
    if not resume and not overwrite and os.path.lexists(out_path):
        raise InputFileError(out_path, "a file already exists here; continue its training with --resume, or start "
                                       "afresh over it with --overwrite")


def train(db, out_path, *, config: TrainConfig | None = None, resume: bool = False, overwrite: bool = False,
          progress: bool = False, log=None, scheduler=None, parts: int = 2, workers: int = 1,
          threads: int | None = None, client=None, device: str = "auto") -> Trainer:
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
    device : {"auto", "cpu", "cuda"}
        Where to train (:func:`resolve_device`); a run resumes on any device.

    With ``config.val_fraction`` > 0 the generator is validated every ``config.val_every``
    iterations and at the end (:meth:`Trainer.validate`); :meth:`Trainer.verdict` then says
    whether its best beat the identity, and the checkpoint records both.
    """
    if client is not None:
        if scheduler is not None:
            raise ParameterError("train: expected scheduler= or its older spelling client=, not both")
        scheduler = client
    if threads is not None and (not _is_int(threads) or threads < 1):
        raise ParameterError(f"threads: expected a positive integer or None, got {threads!r}")
    config = (config or TrainConfig()).check()
    device = resolve_device(device)
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
        if int(saved.get("recipe", 1)) != RECIPE:
            raise InputFileError(out_path, f"config.recipe: trained with recipe {saved.get('recipe', 1)} (before "
                                           f"validation and the balanced losses), this version trains recipe "
                                           f"{RECIPE}; start afresh with --overwrite")
        if "betas" in saved:
            saved["betas"] = tuple(saved["betas"])
        for name in ("w_band", "w_pose"):  # a run from before these terms continues without them
            saved.setdefault(name, 0.0)
        saved.update(iterations=config.iterations, checkpoint_every_s=config.checkpoint_every_s)
        config = TrainConfig(**saved)
    cache = out_path + ".data.h5"
    settings = cache_settings(db, seed=config.seed, window=WINDOW, stride=config.stride,
                              val_fraction=config.val_fraction)
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
                                      workers=workers, progress=report if progress else None, cache=cache,
                                      val_fraction=config.val_fraction)
        finally:
            for b in bars.values():
                b.close()
    features = feature_identity(db)
    cutoff = jitter_cutoff_hz(config, db.fps) or float(db.fps) / 2
    validator = Validator(db, data, cutoff_hz=cutoff) if config.val_fraction > 0 else None
    tr = Trainer(data, config, identity, features, device=device, validator=validator)
    if ck is not None:
        if tr.data.channels != 6 * len(ck["joints"]):
            raise InputFileError(out_path, f"joints: the checkpoint has {len(ck['joints'])} moving joints, the "
                                           f"training data {tr.data.channels // 6}")
        tr.restore(ck, out_path)
        tr.resumed_from = tr.iteration
        if tr.remeasured is not None and log:
            log(f"{out_path}: its verdict predates the guards (docs/refiner.md); its best generator (iteration "
                f"{tr.remeasured}) was measured again on the validation windows")
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=config.iterations, initial=tr.iteration, unit="it", desc=f"training ({device})",
                   disable=None)
    shown = {}  # the last validation numbers, on the progress bar

    def validate():
        m = tr.validate()
        if m is None:
            return
        shown.update(val=f"{m['score']:.3f}", jerk=f"{m['jerk']:.2f}x")
        ident = validator.identity["score"]
        line = (f"validation at iteration {tr.iteration}: {format_metrics(m)}; unrefined score {ident:.3f} "
                f"({100 * (ident - m['score']) / ident:+.1f}% better)")
        if bar is not None:
            bar.write(line, file=sys.stderr)
        elif log:
            log(line)

    if validator is not None:
        if not tr.val_log:
            if log:
                log(f"validation: {validator.n} windows held back (the last {config.val_fraction:.0%} of every "
                    f"recording and its mirror), {len(tr.train_idx)} train; unrefined: "
                    f"{format_metrics(validator.identity)}")
            validate()  # iteration 0: the identity, with the critic of now
    last = logged = time.monotonic()
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
            if validator is not None and tr.iteration % config.val_every == 0:
                validate()
            if bar is not None:
                bar.update(1)
                post = dict(critic=f"{rec['critic']:.3f}", l1=f"{rec['l1']:.3f}", adv=f"{rec['adv']:.3f}",
                            ratio=f"{rec['ratio']:.2g}", **shown)
                bar.set_postfix(**post)
                if bar.disable and log and time.monotonic() - logged >= LOG_EVERY_S:
                    log(f"iteration {tr.iteration}/{config.iterations}: "
                        + ", ".join(f"{k} {v}" for k, v in post.items()))
                    logged = time.monotonic()
            if time.monotonic() - last > config.checkpoint_every_s:
                tr.save(out_path)
                saved_at = tr.iteration
                last = time.monotonic()
    except KeyboardInterrupt:
        tr.save(out_path)  # with the verdict so far
        if log:
            log(f"interrupted at iteration {tr.iteration}: checkpoint saved to {out_path} (continue with --resume)")
        raise
    finally:
        if bar is not None:
            bar.close()
        if old is not None:
            signal.signal(signal.SIGTERM, old)
        torch.set_num_threads(torch_threads)
    if validator is not None and (not tr.val_log or tr.val_log[-1][0] != tr.iteration):
        validate()  # the last iteration is always a candidate
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


#: torch's intra-op threads while refining. A minute of motion is about 10 ms of convolutions on one
#: core; on the shared 2-core machine torch's default two threads made refining 3 to 30 times slower
#: (benchmarks/RESULTS.md), since each waits for the other whenever another process holds a core
REFINE_THREADS = 1


class Refiner:
    """A trained generator that refines whole motions of any length in one pass.

    Use :meth:`refine` directly, or hand the object to
    ``Searcher.synthesize(..., refiner=...)``. ``threads``: torch's intra-op threads while
    refining (:data:`REFINE_THREADS`; torch's own setting is restored after each call).
    """

    def __init__(self, G: Generator, joints: np.ndarray, features: dict, path: str | None = None,
                 validation: dict | None = None, iteration: int | None = None, *, threads: int = REFINE_THREADS):
        if not (_is_int(threads) and threads >= 1):
            raise ParameterError(f"threads: expected a positive integer, got {threads!r}")
        self.G = G.eval()
        self.joints = np.asarray(joints, dtype=np.int64)
        self.features = features
        self.path = path
        self.validation = validation
        self.iteration = iteration  # the checkpoint's last iteration: resuming up to it trains nothing
        self.threads = int(threads)
        #: the checkpoint keeps the identity (its verdict: no trained generator beat it): refine() is a no-op
        self.is_identity = False
        # which of the represented joints refining changes (all but the legs), found once: refine()
        # checks that a motion's skeleton is the one of ``features``
        legs = set(int(j) for j in leg_joints(features["joint_names"], features["parents"]))
        self._kept = np.array([i for i, j in enumerate(self.joints.tolist()) if j not in legs], dtype=np.int64)
        self._rows = torch.from_numpy((6 * self._kept[:, None] + np.arange(6)).ravel())

    @classmethod
    def load(cls, path, db=None) -> "Refiner":
        """The checkpoint's best generator by validation (its last one when it has no validation),
        on the CPU whatever device trained it."""
        ck = read_checkpoint(path)  # every entry used below is checked there, the width bounded
        if db is not None:
            check_compatible(ck, db, path)
        cfg = ck["config"]
        joints = ck["joints"].numpy()
        G = make_generator(cfg, ck["features"], joints, 6 * len(joints), int(ck["features"]["audio_channels"]))
        which = "best_generator" if "best_generator" in ck else "generator"
        _load_state(G, ck[which], os.fspath(path), which)
        it = ck.get("iteration")
        out = cls(G, joints, ck["features"], os.fspath(path), ck.get("validation"), it if _is_int(it) else None)
        best = (ck.get("validation") or {}).get("best") or {}
        # the identity kept (no trained generator was better): refine() returns its input as it is, not
        # through the 6D round trip (float32: evaluated metrics moved by up to 0.05 %)
        out.is_identity = which == "best_generator" and best.get("iteration") == 0
        return out

    @property
    def verdict(self) -> dict | None:
        """The validation verdict the checkpoint records (None: trained without validation)."""
        return (self.validation or {}).get("verdict")

    def assess(self) -> tuple[str, str]:
        """``("better" | "worse" | "unknown", one line)``: whether this refiner beat the identity on its
        validation windows, for ``synth --refiner`` to refuse by (all but "better", unless ``--force``).

        "unknown": no verdict (``--val-fraction 0``, or a checkpoint from before validation), or one
        recorded before the verdict's guards existed (:func:`~gesturedb.refiner.validation.missing_guards`),
        whose "better" may be one the guards refuse; the line says what is missing and how to measure it."""
        v = self.verdict
        name = self.path or "refiner"
        if v is None:
            return "unknown", (f"{name}: no validation verdict (trained with --val-fraction 0, or before "
                               "validation existed): whether it improves on the unrefined motion is unknown; "
                               "train one with validation (refiner train --val-fraction, default 0.25)")
        pct = 100 * v["improvement"]
        missing = missing_guards(v)
        if missing:
            said = "better" if v["beats_identity"] else "not better"
            again = f" --iterations {self.iteration}" if self.iteration is not None else ""
            return "unknown", (f"{name}: its validation verdict ({said}: score {pct:+.1f}% at iteration "
                               f"{v['best_iteration']}) was recorded without the guards a verdict needs now, so "
                               f"whether it improves on the unrefined motion is unknown: it did not check "
                               f"{', '.join(GUARDS[k] for k in missing)}; `gesturedb refiner train DB.h5 -o {name} "
                               f"--resume{again}` on the database it was trained on measures it again")
        if v.get("identity_kept"):
            t = v.get("trained") or {}
            why = (f" (the closest, iteration {t['iteration']}: score {100 * t['improvement']:+.1f}%"
                   + (f", worse on {describe_worse(t['worse'])}" if t.get("worse") else "") + ")") if t else ""
            return "worse", (f"{name}: no trained generator beat the unrefined motion on its validation windows"
                             f"{why}; the checkpoint keeps the identity: refining with it changes nothing")
        if v.get("worse"):
            return "worse", (f"{name}: did not beat the unrefined motion on its validation windows: its score is "
                             f"{pct:.1f}% lower (iteration {v['best_iteration']}) but it is worse on "
                             f"{describe_worse(v['worse'])}")
        if v["beats_identity"]:
            return "better", (f"{name}: beat the unrefined motion on its validation windows by {pct:.1f}% "
                              f"(iteration {v['best_iteration']})")
        return "worse", (f"{name}: did not beat the unrefined motion on its validation windows (best score "
                         f"{v['best_score']:.3f} at iteration {v['best_iteration']} vs {v['identity_score']:.3f} "
                         f"unrefined, {pct:+.1f}%; {100 * v.get('margin', 0):.0f}% better needed)")

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
            above the hips (the legs keep the input's planted feet). A copy of the input
            when the checkpoint keeps the identity (:attr:`is_identity`).
        """

        T = motion.rotations.shape[0]
        audio = np.asarray(audio, dtype=np.float32)
        if audio.shape != (T, int(self.features["audio_channels"])):
            raise ParameterError(f"audio: expected ({T}, {self.features['audio_channels']}) features for "
                                 f"{T} frames; got {audio.shape}")
        if list(motion.skeleton.names) != list(self.features["joint_names"]):
            raise GestureDBError(f"refiner {self.path}: motion skeleton has joints {len(motion.skeleton.names)}, "
                                 f"the refiner was trained for {len(self.features['joint_names'])}")
        if self.is_identity:
            return Motion(skeleton=motion.skeleton, fps=motion.fps, rotations=motion.rotations.copy(),
                          root_positions=motion.root_positions.copy())
        before = torch.get_num_threads()
        if before != self.threads:  # setting it costs a little even when unchanged
            torch.set_num_threads(self.threads)
        try:
            x = to_channels_torch(motion.rotations, self.joints)
            a = torch.from_numpy(np.ascontiguousarray(audio.T[None]))
            with torch.inference_mode():  # no autograd bookkeeping at all (no_grad still tracks versions)
                # the legs stay the k-NN's: assembly planted the feet with leg IK, and a refined leg
                # would slide them again (measured: skating 0.05 -> 0.18 m/s on held-out speech);
                # so only the other joints' channels are turned back into rotations, and the legs
                # keep the input's (from_channels_torch copies every joint it is not given)
                y = self.G(a, x)[0].index_select(0, self._rows)
                rot = from_channels_torch(y, motion.rotations, self.joints[self._kept])
        finally:
            if before != self.threads:
                torch.set_num_threads(before)
        return Motion(skeleton=motion.skeleton, fps=motion.fps, rotations=rot, root_positions=motion.root_positions)
