"""The cGAN refiner (Habibie et al. 2022, Sec. 3.2): smooths and resynchronises k-NN output.

The only part of gesturedb that imports torch; it is an optional extra
(``pip install '.[refiner]'``, which pins the CPU build ``torch==2.13.0``; training
also runs on a CUDA GPU with a CUDA build of torch, ``--device``).
Importing this package does not import torch: its modules do, when used.

=====================  =====================================================
``representation``     motion <-> network channels (6D local rotations; numpy)
``model``              generator, discriminator, critic augmentation (torch)
``data``               training windows: real pairs and k-NN fakes (cached),
                       the validation split
``validation``         validation metrics, score and verdict (numpy)
``checkpoint``         settings (:class:`TrainConfig`), reading checkpoints
``train``              WGAN-GP training on CPU or CUDA, validation, resume;
                       :class:`Refiner`
=====================  =====================================================

    from gesturedb.refiner import load_refiner
    refiner = load_refiner("refiner.pt", db)          # checks skeleton and features
    result = Searcher(db).synthesize("speech.wav", refiner=refiner)
"""
from __future__ import annotations

from gesturedb.refiner._torch import INSTALL_HINT, require_torch


def load_refiner(path, db=None):
    """Load a trained refiner checkpoint (no code is executed from the file); see :class:`train.Refiner`."""
    require_torch()
    # local on purpose: refiner.train imports torch at its top, and `import gesturedb.refiner` stays torch-free
    from gesturedb.refiner.train import Refiner

    return Refiner.load(path, db=db)


__all__ = ["INSTALL_HINT", "load_refiner", "require_torch"]
