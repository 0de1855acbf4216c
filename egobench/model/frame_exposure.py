"""A per-frame exposure correction learned with the scene (`TrainConfig.learn_frame_exposure`): each training
frame's exposure x gain normaliser k times exp(s), s the frame's trainable log scale (zero: the record is right).

Why: a record that is wrong on some frames makes their images brighter or darker than the model predicts, and a
shared scene absorbs part of that where the content is seen mostly in those frames (the diagnosis's records test
then sees only the rest). With a parameter of its own per frame, the wrong record is that frame's to explain.
"""

from __future__ import annotations

from torch import Tensor

#: the trainable's key in a run's ``extra`` (a [F] log scale, F training frames in the trainer's order)
KEY = "frame_exposure"


def corrected_normaliser(k: Tensor | float, extra: dict, fi: int) -> Tensor | float:
    """Training frame ``fi``'s normaliser ``k`` times its learned exposure correction (``k`` itself without one)."""
    scale = extra.get(KEY)
    return k if scale is None else k * scale[fi].exp()


__all__ = ["KEY", "corrected_normaliser"]
