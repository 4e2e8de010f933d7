"""Generator and discriminator of the refiner (Habibie et al. 2022, Sec. 3.2), fully convolutional in time.

Tensors are ``(batch, channels, T)``; audio has 28 channels (14 standardised
MFCC + log energy and their first derivatives, as stored in the database),
gestures ``C_g = 6 * Jm`` (see :mod:`gesturedb.refiner.representation`).

Deviations from the paper, each for a stated reason:

- The generator predicts a *correction* added to the k-NN gesture (its last
  block, a single Conv1d, starts at zero). At initialisation the refiner is the
  identity, so a short CPU training run can only improve on the k-NN input and
  never starts from noise; the L1 term to the k-NN input (w1) keeps the same
  meaning.
- The discriminator averages its features over time before the fully
  connected layer, so it accepts any T (the paper trains on fixed 64-frame
  windows; at T = 64 this is a fixed pooling).
- Any T: the input is padded (edge values repeated) to a multiple of the
  generator's pooling factor 8 and the output cropped back.
- Channels of ``frozen`` joints (the legs, which the assembly planted and
  refining puts back) get no correction: the critic never sees them either.
"""
from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

AUDIO_CHANNELS = 28
POOL_FACTOR = 8  # max pooling after blocks 2, 4 and 6 of the encoder
#: the bands (Hz) whose power per joint the band-power term keeps: below the stroke bands (sway, slow
#: drift; the mean left out), the three stroke bands of gesturedb.measures.BANDS_HZ, and the rest
BAND_EDGES_HZ = ((0.0, 0.5), (0.5, 2.0), (2.0, 4.0), (4.0, float("inf")))


def _block(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv1d(c_in, c_out, 3, padding=1), nn.BatchNorm1d(c_out), nn.ReLU(inplace=True))


class Generator(nn.Module):
    """Encoder of 8 [Conv1d, BatchNorm1d, ReLU] blocks with max pooling after every second block
    except the last; decoder of 8 blocks mirroring it with upsampling after every second block,
    the last block a single Conv1d.

    Parameters
    ----------
    gesture_channels : int
        ``C_g``.
    width : int
        Channels of the hidden blocks.
    """

    def __init__(self, gesture_channels: int, *, audio_channels: int = AUDIO_CHANNELS, width: int = 128,
                 frozen=None):
        super().__init__()
        self.gesture_channels = gesture_channels
        c_in = audio_channels + gesture_channels
        self.enc = nn.ModuleList([_block(c_in if i == 0 else width, width) for i in range(8)])
        self.dec = nn.ModuleList([_block(width, width) for _ in range(7)])
        self.out = nn.Conv1d(width, gesture_channels, 3, padding=1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        # fixed, derived from the checkpoint's settings: buffers outside the state dict
        keep = torch.ones(gesture_channels)
        if frozen is not None:
            keep[torch.as_tensor(frozen, dtype=torch.long)] = 0.0
        self.register_buffer("keep", keep[:, None], persistent=False)

    def correction(self, audio: torch.Tensor, gesture: torch.Tensor) -> torch.Tensor:
        """(B, C_g, T): what the generator adds to ``gesture`` (zero on frozen channels)."""
        T = gesture.shape[-1]
        pad = (-T) % POOL_FACTOR
        a = F.pad(audio, (0, pad), mode="replicate") if pad else audio
        g = F.pad(gesture, (0, pad), mode="replicate") if pad else gesture
        h = torch.cat([a, g], dim=1)
        for i, blk in enumerate(self.enc):
            h = blk(h)
            if i % 2 == 1 and i < 7:
                h = F.max_pool1d(h, 2)
        for i, blk in enumerate(self.dec):
            h = blk(h)
            if i % 2 == 0 and i < 6:  # three upsamplings undo the three poolings
                h = F.interpolate(h, scale_factor=2, mode="linear", align_corners=False)
        return self.out(h)[..., :T] * self.keep

    def forward(self, audio: torch.Tensor, gesture: torch.Tensor) -> torch.Tensor:
        return gesture + self.correction(audio, gesture)


class Discriminator(nn.Module):
    """6 [Conv1d, InstanceNorm1d, LeakyReLU] blocks with average pooling after every second block,
    then a fully connected layer to one scalar (the WGAN critic's score) per sequence."""

    def __init__(self, gesture_channels: int, *, audio_channels: int = AUDIO_CHANNELS, width: int = 128):
        super().__init__()
        c_in = audio_channels + gesture_channels
        self.blocks = nn.ModuleList([
            nn.Sequential(nn.Conv1d(c_in if i == 0 else width, width, 3, padding=1),
                          nn.InstanceNorm1d(width, affine=True), nn.LeakyReLU(0.2, inplace=True))
            for i in range(6)
        ])
        self.fc = nn.Linear(width, 1)

    def forward(self, audio: torch.Tensor, gesture: torch.Tensor) -> torch.Tensor:
        h = torch.cat([audio, gesture], dim=1)
        for i, blk in enumerate(self.blocks):
            h = blk(h)
            if i % 2 == 1 and h.shape[-1] >= 2:
                h = F.avg_pool1d(h, 2)
        return self.fc(h.mean(dim=-1)).squeeze(-1)


def gradient_penalty(critic, real_audio: torch.Tensor, real: torch.Tensor, fake_audio: torch.Tensor,
                     fake: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """WGAN-GP term (Gulrajani et al. 2017) of a conditional critic.

    Mean over the batch of ``(||grad D(a, x)|| - 1)^2`` at the interpolates
    ``a = eps * real_audio + (1 - eps) * fake_audio``, ``x = eps * real + (1 - eps) * fake``;
    the norm is over both inputs, since the critic is Lipschitz in the pair.
    ``eps`` is (B, 1, 1), uniform in [0, 1].
    """
    a = (eps * real_audio + (1 - eps) * fake_audio).requires_grad_(True)
    x = (eps * real + (1 - eps) * fake).requires_grad_(True)
    score = critic(a, x)
    ga, gx = torch.autograd.grad(score.sum(), (a, x), create_graph=True)
    norm = torch.sqrt(ga.flatten(1).pow(2).sum(1) + gx.flatten(1).pow(2).sum(1))
    return ((norm - 1) ** 2).mean()


def augment(audio: torch.Tensor, gesture: torch.Tensor, gen: torch.Generator, *, crop: float,
            warp: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Random crops with small time warps of (audio, gesture) pairs, for the critic.

    Each sequence of the batch is resampled (linear interpolation, differentiable) from a
    random stretch of ``crop * T * s`` frames to ``round(crop * T)`` frames, ``s`` uniform in
    ``[1 - warp, 1 + warp]`` (capped at T): audio and gesture together, so they stay
    aligned. With 264 windows the critic learns every real window by heart (its gap grew
    on training windows and stayed at 0 on validation ones); shifted, shorter and slightly
    faster or slower copies of them are many more windows. The random numbers come from
    ``gen`` (on the CPU, so a run resumes on another device with the same draws).

    Parameters
    ----------
    audio : (B, A, T), gesture : (B, C, T) tensors on one device
    crop : float in (0, 1]; warp : float in [0, 1)
    """
    B, _, T = gesture.shape
    L = max(2, min(T, int(round(crop * T))))
    if L == T and warp == 0:
        return audio, gesture
    u = torch.rand(B, 2, generator=gen)
    src = torch.clamp(L * (1 + warp * (2 * u[:, 0] - 1)), max=float(T))  # source frames spanned
    start = u[:, 1] * (T - src)
    pos = start[:, None] + torch.arange(L, dtype=torch.float32)[None] * ((src - 1) / (L - 1))[:, None]
    pos = pos.clamp(0, T - 1).to(gesture.device)
    i0 = pos.floor().long().clamp(max=T - 2)
    w = (pos - i0)[:, None]

    def take(x):
        idx = i0[:, None].expand(-1, x.shape[1], -1)
        return torch.gather(x, 2, idx) * (1 - w) + torch.gather(x, 2, idx + 1) * w

    return take(audio), take(gesture)


def high_band_energy(x: torch.Tensor, fps: float, cutoff_hz: float) -> torch.Tensor:
    """(B, C): energy of each channel of ``x`` (B, C, T) at and above ``cutoff_hz`` (Parseval: the sum of
    squares of the high-passed signal), its mean over time removed."""
    spec = torch.fft.rfft(x - x.mean(dim=-1, keepdim=True), dim=-1)
    f = torch.fft.rfftfreq(x.shape[-1], d=1.0 / fps).to(x.device)
    w = (f >= cutoff_hz).to(x.dtype) * 2.0  # one-sided spectrum: every bin but 0 and Nyquist counts twice
    if x.shape[-1] % 2 == 0:
        w[-1] = w[-1] / 2
    return (spec.real ** 2 + spec.imag ** 2).mul(w).sum(-1) / x.shape[-1]


def band_powers(x: torch.Tensor, fps: float, edges_hz) -> torch.Tensor:
    """(B, C, K): power of each channel of ``x`` (B, C, T) in each band ``[lo, hi)`` of ``edges_hz``
    (K pairs of Hz; a band from 0 leaves out the mean, bin 0): the mean square of the signal's
    part in that band (Parseval: bands that cover (0, inf) sum to the variance over time). A band
    with no frequency bin at this length (below 1 / T) has power 0."""
    spec = torch.fft.rfft(x - x.mean(dim=-1, keepdim=True), dim=-1)
    p = (spec.real ** 2 + spec.imag ** 2) / x.shape[-1] ** 2
    f = torch.fft.rfftfreq(x.shape[-1], d=1.0 / fps).to(x.device)
    twice = torch.full_like(f, 2.0)  # one-sided spectrum: every bin but 0 and Nyquist counts twice
    twice[0] = 1.0
    if x.shape[-1] % 2 == 0:
        twice[-1] = 1.0
    w = torch.stack([((f > 0) & (f >= lo) & (f < hi)).to(x.dtype) * twice for lo, hi in edges_hz], dim=1)  # (F, K)
    return p @ w.to(p.dtype)


def band_change(out: torch.Tensor, inp: torch.Tensor, fps: float) -> torch.Tensor:
    """The band-power term: mean over windows, joints and :data:`BAND_EDGES_HZ` of ``|log(P_out / P_in)|``,
    how far the output's power per joint and band (its 6 channels summed) is from its input's.

    ``out``, ``inp``: (B, 6 J, T) gesture channels, 6 per joint. Two-sided: the first recipe's best
    generator lowered the arms' speeds 5-7 % and raised the neck's, head's and collars' 15-19 %
    (validation windows), which moved H(speed) against the database, whose speeds the k-NN's are
    close to. ``eps`` (a thousandth of the window's mean power in that band) keeps still joints
    from dominating through ratios of near-zeros; a band without a frequency bin at this length
    (below 1/T) is left out rather than counted as no change.
    """
    def per_joint(x):
        p = band_powers(x, fps, BAND_EDGES_HZ)                   # (B, C, K)
        return p.reshape(p.shape[0], -1, 6, p.shape[-1]).sum(2)  # (B, J, K)

    p_out, p_in = per_joint(out), per_joint(inp)
    eps = 1e-3 * p_in.mean(dim=1, keepdim=True) + 1e-12
    f = torch.fft.rfftfreq(out.shape[-1], d=1.0 / fps)
    has = [k for k, (lo, hi) in enumerate(BAND_EDGES_HZ) if bool(((f > 0) & (f >= lo) & (f < hi)).any())]
    return torch.log((p_out + eps) / (p_in + eps))[..., has].abs().mean()
