"""Self-trained Fréchet gesture distance (FGD*): GENEA's recipe with an autoencoder trained on the database.

The FGD of the GENEA challenges is the Fréchet distance between Gaussians fitted to the
autoencoder codes of real and generated motion windows. Here the autoencoder
(:mod:`gesturedb.refiner.autoencoder`, torch) is trained on the database's own motion
when an evaluation starts, so the numbers compare systems with each other on this
database and are **not comparable with published FGD values** (other training data,
joints, window length and code size). Reported as ``fgd_self_gt`` (against the ground
truth's windows) and ``fgd_self_db`` (against the database's), marked FGD* in tables.

Windows: 32 frames of the upper-body joints' positions with the root's horizontal
position removed (the arrays the other upper-body metrics use) and their velocities
(m/s; without them the encoder, which smooths, scarcely sees jitter), every 4 frames.
Codes are divided by the database codes' standard deviation per dimension, so a
distance reads in units of the database's own spread (0: the same distribution).
Without torch the columns are NaN (the refiner extra installs it).
"""
from __future__ import annotations

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.eval.common import metric_positions
from gesturedb.measures import FGD_STRIDE, frechet_distance, motion_windows  # one home, shared with the refiner
from gesturedb.refiner.autoencoder import WINDOW, train_motion_encoder

__all__ = ["frechet_distance", "motion_windows", "SelfFGD", "STRIDE"]

#: frames between window starts
STRIDE = FGD_STRIDE
_CACHE: dict = {}


class SelfFGD:
    """The autoencoder trained on a database's recordings, and the codes of its windows.

    Parameters
    ----------
    db : gesturedb.db.database.Database
    joints : int array, the upper-body joints; root : int
    seed : int, training seed (the distance is deterministic for a seed)
    """

    def __init__(self, db, *, joints, root: int, seed: int = 0):
        self.joints = np.asarray(joints)
        self.fps = float(db.fps)
        wins = [motion_windows(metric_positions(db.joint_positions[r.start_frame:r.stop_frame], root),
                               joints=self.joints, window=WINDOW, fps=self.fps)
                for r in db.recordings]  # within recordings: no window spans two
        wins = np.concatenate(wins) if wins else np.zeros((0, WINDOW, 6 * len(self.joints)), np.float32)
        if wins.shape[0] < 8:
            raise ParameterError(f"database: expected at least 8 windows of {WINDOW} frames for the FGD "
                                 f"autoencoder, got {wins.shape[0]}")
        self.model = train_motion_encoder(wins, seed=seed)
        raw = self.model.encode(wins)
        self.code_std = np.maximum(raw.std(0), 1e-9)
        self.db_codes = raw / self.code_std

    @classmethod
    def try_build(cls, db, *, joints, root: int, seed: int = 0):
        """A SelfFGD, or None when torch is not installed (the columns are then NaN).

        Kept per process for a database file (path, size, modification time), joints and
        seed, so repeated evaluations of one database train once.
        """
        import importlib.util
        import os

        if importlib.util.find_spec("torch") is None:  # looked up, not imported: only the refiner imports torch
            return None
        try:
            st = os.stat(db.path)
            key = (os.path.abspath(db.path), st.st_size, st.st_mtime_ns, tuple(int(j) for j in joints), int(root),
                   int(seed))
        except (OSError, TypeError):
            key = None
        if key is not None and key in _CACHE:
            return _CACHE[key]
        out = cls(db, joints=joints, root=root, seed=seed)
        if key is not None:
            _CACHE.clear()  # one database at a time: the codes and network are small, but need not pile up
            _CACHE[key] = out
        return out

    def codes(self, positions: np.ndarray) -> np.ndarray:
        """Codes (n, LATENT), in database standard deviations, of root-relative positions (T, J, 3)
        (``metric_positions``) at the database's frame rate."""

        w = motion_windows(positions, joints=self.joints, window=WINDOW, fps=self.fps)
        if w.shape[0] == 0:
            return np.zeros((0, self.db_codes.shape[1]))
        return self.model.encode(w) / self.code_std
