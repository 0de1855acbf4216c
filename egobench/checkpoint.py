"""Reading checkpoint files safely: tensors and plain containers only, one-line errors.

Every checkpoint egobench reads goes through `read_checkpoint`: ``torch.load`` with
``weights_only=True`` (a user's file never runs pickled code) and ``map_location="cpu"``. A
truncated, foreign or tampered file raises ValueError naming the file and what was expected, in
one line (the CLI prints it without a traceback).
"""

from __future__ import annotations

import pickle
import re
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
        raise ValueError(f"{path}: unreadable checkpoint: {_why_unreadable(path, exc)}; delete it and train again") from None
    if not isinstance(ck, dict):
        raise ValueError(f"{path}: unreadable checkpoint: expected a dict of tensors, got {type(ck).__name__}")
    return ck


def _why_unreadable(path: Path, exc: BaseException) -> str:
    """Why ``torch.load(weights_only=True)`` refused ``path``: code refused, or not a checkpoint at all."""
    text = str(exc)
    if re.search(r"\bGLOBAL\b|allowed global|Unsupported global", text):
        return "it holds objects other than tensors and plain containers (refused: loading it could run code)"
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    detail = next((ln for ln in lines if ln.startswith(("Unsupported", "invalid load key"))), lines[0] if lines else "")
    with open(path, "rb") as fh:
        head = fh.read(2)
    kind = ("a zip archive" if head == b"PK" or zipfile.is_zipfile(path) else
            "a pickle stream" if head[:1] == b"\x80" else None)
    what = f"{kind} that is truncated or corrupt" if kind else "neither a torch zip archive nor a pickle (foreign bytes)"
    return f"not a checkpoint: {what} ({type(exc).__name__}: {detail[:160]})"
