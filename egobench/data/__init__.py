"""Recordings: in-memory form (`Recording`), MPS files, the authors' format, `load_recording`."""

from egobench.data.reader import load_recording
from egobench.data.recording import HOLDOUT_EVERY, Frame, Recording, SparseDepth

__all__ = ["load_recording", "Recording", "Frame", "SparseDepth", "HOLDOUT_EVERY"]
