"""The one trainer: every method of `egobench.model.methods` is a set of switches read here.

Modules, one concern each:
    config      `TrainConfig`, presets, ``--set`` overrides
    data        a recording validated and loaded at the training resolution (uint8 image store)
    initialise  Gaussians from the semi-dense points
    state       parameters, optimisers, densifier, RNG: `TrainState` and its checkpoint dict
    checkpoint  checkpoint.pt read (safely) and written; a trained run loaded for rendering
    losses      photometric loss, 2DGS regularisers
    loop        `train_step` and `train`
    record      train.json
    cli         ``egobench train``
The per-frame render path (poses, rolling-shutter gather, formation) is `egobench.model.predict`,
shared with evaluation and diagnosis.
"""

from __future__ import annotations

import importlib

#: public name -> the module that defines it (imported on first use: ``egobench.train.cli`` stays light)
_EXPORTS = {
    "CHECKPOINT_FORMAT": "checkpoint", "TrainedRun": "checkpoint", "load_trained_run": "checkpoint",
    "read_run_checkpoint": "checkpoint", "PAPER_ITERATIONS": "config", "PRESETS": "config", "TrainConfig": "config",
    "parse_overrides": "config", "preset_config": "config", "TrainingData": "data", "load_image_store": "data",
    "prepare_data": "data", "TrainingDiverged": "loop", "TrainResult": "record", "train": "loop",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'egobench.train' has no attribute {name!r}")
    return getattr(importlib.import_module(f"egobench.train.{_EXPORTS[name]}"), name)
