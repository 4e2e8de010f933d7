"""A motion autoencoder trained on the database itself: the feature space of the self-trained FGD.

GENEA's recipe for a Fréchet gesture distance (Yoon et al. 2020; the GENEA challenges)
trains an autoencoder on motion windows and compares the distributions of its codes.
Published FGD values use autoencoders trained on other data and other joints, so a
distance computed with this one is **not comparable** with them: it compares systems
with each other on one database (:mod:`gesturedb.eval.fgd`).

Lives in the refiner package because it needs torch (the only torch user, see
``.importlinter``); it is independent of the refiner's networks.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.refiner._torch import require_torch

__all__ = ["MotionEncoder", "train_motion_encoder", "WINDOW", "LATENT"]

#: frames per window (about 2 s at 15 fps: a gesture phrase)
WINDOW = 32
#: code size; small, since an evaluation has a few dozen to a few hundred windows to
#: estimate each covariance from
LATENT = 16


def _networks(dim: int, latent: int, hidden: int):
    torch = require_torch()
    nn = torch.nn
    # three stride-2 convolutions: 32 frames -> 4, then a linear layer to the code
    enc = nn.Sequential(
        nn.Conv1d(dim, hidden, 4, 2, 1), nn.LeakyReLU(0.2),
        nn.Conv1d(hidden, hidden, 4, 2, 1), nn.LeakyReLU(0.2),
        nn.Conv1d(hidden, hidden, 4, 2, 1), nn.LeakyReLU(0.2),
        nn.Flatten(), nn.Linear(hidden * (WINDOW // 8), latent),
    )
    dec = nn.Sequential(
        nn.Linear(latent, hidden * (WINDOW // 8)), nn.Unflatten(1, (hidden, WINDOW // 8)), nn.LeakyReLU(0.2),
        nn.ConvTranspose1d(hidden, hidden, 4, 2, 1), nn.LeakyReLU(0.2),
        nn.ConvTranspose1d(hidden, hidden, 4, 2, 1), nn.LeakyReLU(0.2),
        nn.ConvTranspose1d(hidden, dim, 4, 2, 1),
    )
    return enc, dec


@dataclass
class MotionEncoder:
    """The trained encoder and the standardisation of its inputs.

    ``encode(windows (n, WINDOW, D)) -> (n, LATENT)`` float64; ``loss`` is the final
    reconstruction error (mean squared, standardised units).
    """

    encoder: object
    mean: np.ndarray
    std: np.ndarray
    loss: float

    def encode(self, windows: np.ndarray) -> np.ndarray:
        torch = require_torch()
        w = np.asarray(windows, dtype=np.float32)
        if w.ndim != 3 or w.shape[1] != WINDOW or w.shape[2] != self.mean.shape[0]:
            raise ParameterError(f"windows: expected shape (n, {WINDOW}, {self.mean.shape[0]}), got {w.shape}")
        x = _channels(torch, w, self.mean, self.std)
        with torch.no_grad():
            return self.encoder(x).double().numpy()


def train_motion_encoder(windows: np.ndarray, *, steps: int = 600, batch: int = 64, lr: float = 2e-3,
                         hidden: int = 32, latent: int = LATENT, seed: int = 0) -> MotionEncoder:
    """Train the autoencoder on database windows (n, WINDOW, D) (deterministic for a seed).

    Each dimension is standardised over the training windows. Adam, ``steps`` minibatches of
    ``batch`` windows, mean squared reconstruction error, on one thread (an evaluation
    trains it once: a few seconds for a 2-minute database).
    """
    torch = require_torch()
    w = np.asarray(windows, dtype=np.float32)
    if w.ndim != 3 or w.shape[1] != WINDOW or w.shape[0] < 2:
        raise ParameterError(f"windows: expected at least 2 windows of shape ({WINDOW}, D), got {w.shape}")
    if not np.isfinite(w).all():
        raise ParameterError("windows: expected finite positions, got NaN or inf")
    mean = w.mean(axis=(0, 1))
    std = np.maximum(w.std(axis=(0, 1)), 1e-4)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small convolutions: threads cost more than they give; restored below
    try:
        return _train(torch, w, mean, std, steps=steps, batch=batch, lr=lr, hidden=hidden, latent=latent, seed=seed)
    finally:
        torch.set_num_threads(threads)


def _channels(torch, w, mean, std):
    """Standardised windows (n, WINDOW, D) as a float32 tensor (n, D, WINDOW), channels first for Conv1d."""
    return torch.from_numpy(((w - mean) / std).transpose(0, 2, 1).copy())


def _train(torch, w, mean, std, *, steps, batch, lr, hidden, latent, seed) -> MotionEncoder:
    x = _channels(torch, w, mean, std)
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    enc, dec = _networks(w.shape[2], latent, hidden)
    opt = torch.optim.Adam(list(enc.parameters()) + list(dec.parameters()), lr=lr)
    for _ in range(steps):
        idx = torch.randint(0, x.shape[0], (min(batch, x.shape[0]),), generator=gen)
        xb = x[idx]
        loss = torch.mean((dec(enc(xb)) - xb) ** 2)
        opt.zero_grad()
        loss.backward()
        opt.step()
    enc.eval()
    with torch.no_grad():
        final = float(torch.mean((dec(enc(x)) - x) ** 2))
    return MotionEncoder(encoder=enc, mean=mean, std=std, loss=final)
