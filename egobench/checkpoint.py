"""Reading checkpoint files safely: tensors and plain containers only, one-line errors.

Every checkpoint egobench reads goes through `read_checkpoint`: ``torch.load`` with
``weights_only=True`` (a user's file never runs pickled code) and ``map_location="cpu"``. A
truncated, foreign or tampered file raises ValueError naming the file and what was expected, in
one line (the CLI prints it without a traceback).
"""

from __future__ import annotations

import pickle
import struct
import zipfile
from pathlib import Path

import torch


def read_checkpoint(path: str | Path) -> dict:
    """The checkpoint dict at ``path`` (tensors on the CPU); ValueError if unreadable or not a dict."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint not found")
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError, zipfile.BadZipFile, ValueError,
            AttributeError, TypeError, KeyError, IndexError, struct.error) as exc:
        lines = str(exc).strip().splitlines()
        first = lines[0] if lines else type(exc).__name__
        if "weights_only" in str(exc) or isinstance(exc, pickle.UnpicklingError):
            why = "it holds objects other than tensors and plain containers (refused: loading it could run code)"
        else:
            why = f"truncated or not a torch checkpoint ({type(exc).__name__}: {first[:160]})"
        raise ValueError(f"{path}: unreadable checkpoint: {why}; delete it and train again") from None
    if not isinstance(ck, dict):
        raise ValueError(f"{path}: unreadable checkpoint: expected a dict of tensors, got {type(ck).__name__}")
    return ck
