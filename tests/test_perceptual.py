"""LPIPS (AlexNet, v0.1) offline: the restricted loader, the weight layout, the heads against
torchmetrics' bundled v0.1 heads, and the full metric against the reference implementation's
published example distances."""

from __future__ import annotations

import hashlib
import importlib.util
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

FIXTURES = Path(__file__).parent / "fixtures" / "lpips"


class _RunsCode:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_the_loader_refuses_a_pickle_that_carries_code(tmp_path):
    from egobench.perceptual import read_arrays_pickle

    marker = tmp_path / "ran"
    data = pickle.dumps({"AlexNet_0": {"Conv_0": {"kernel": _RunsCode(marker)}}})
    with pytest.raises(ValueError, match=r"refused global pathlib\.Path\.touch|refused global pathlib"):
        read_arrays_pickle(data, "evil.ckpt")
    assert not marker.exists()
    arrays = read_arrays_pickle(pickle.dumps({"a": {"b": np.arange(6.0).reshape(2, 3)}}), "ok.ckpt")
    np.testing.assert_array_equal(arrays["a/b"], np.arange(6.0).reshape(2, 3))
    with pytest.raises(ValueError, match="a/c is a list, expected numpy arrays only"):
        read_arrays_pickle(pickle.dumps({"a": {"c": [1, 2]}}), "list.ckpt")


def _flax_tree(rng):
    from egobench.perceptual import CONVS

    tree = {"AlexNet_0": {}}
    for i, (c_out, c_in, k, _, _) in enumerate(CONVS):
        tree["AlexNet_0"][f"Conv_{i}"] = {"kernel": rng.normal(size=(k, k, c_in, c_out)).astype(np.float32),
                                          "bias": rng.normal(size=c_out).astype(np.float32)}
        tree[f"NetLinLayer_{i}"] = {"Conv_0": {"kernel": rng.random(size=(1, 1, c_out, 1)).astype(np.float32)}}
    return tree


def test_install_checks_the_digest_and_transposes_flax_kernels(tmp_path, monkeypatch):
    from egobench.perceptual import _model, install_weights, weights_file

    monkeypatch.setenv("EGOBENCH_CACHE", str(tmp_path / "cache"))
    tree = _flax_tree(np.random.default_rng(0))
    ckpt = tmp_path / "alexnet.ckpt"
    ckpt.write_bytes(pickle.dumps(tree))
    with pytest.raises(ValueError, match="has SHA-256 .* expected"):
        install_weights(ckpt)
    assert not weights_file().exists()
    out = install_weights(ckpt, sha256=hashlib.sha256(ckpt.read_bytes()).hexdigest())
    with np.load(out) as z:
        w = z["conv1.weight"]  # [out, in, kh, kw] from flax's [kh, kw, in, out]
        assert w.shape == (192, 64, 5, 5) and w[7, 3, 1, 4] == tree["AlexNet_0"]["Conv_1"]["kernel"][1, 4, 3, 7]
        assert z["lin2.weight"].shape == (1, 384, 1, 1)
    _model.cache_clear()


def _weights_or_skip():
    from egobench.perceptual import _model, available

    ok, reason = available()
    if not ok:
        pytest.skip(reason)
    _model.cache_clear()
    return _model()


def test_the_heads_equal_torchmetrics_bundled_v01_heads():
    model = _weights_or_skip()
    spec = importlib.util.find_spec("torchmetrics")
    if spec is None:
        pytest.skip("torchmetrics (a test dependency) is not installed")
    path = Path(spec.submodule_search_locations[0]) / "functional" / "image" / "lpips_models" / "alex.pth"
    heads = torch.load(path, map_location="cpu", weights_only=True)
    for i in range(5):
        torch.testing.assert_close(model.lins[i].weight, heads[f"lin{i}.model.1.weight"], rtol=0, atol=0)


def _patch(name: str) -> torch.Tensor:
    img = cv2.cvtColor(cv2.imread(str(FIXTURES / f"{name}.png")), cv2.COLOR_BGR2RGB)
    return torch.from_numpy(img).float() / 255.0


def test_the_reference_example_distances():
    """The reference implementation's test_network.py (alex, v0.1, spatial): (0.722, 0.138)."""
    model = _weights_or_skip()
    from egobench.perceptual import lpips_alex

    ref, p0, p1 = (_patch(n) for n in ("ex_ref", "ex_p0", "ex_p1"))
    net = lambda x: x.permute(2, 0, 1)[None] * 2 - 1  # noqa: E731
    with torch.no_grad():
        d0, d1 = (float(model(net(ref), net(p), spatial=True)[0]) for p in (p0, p1))
    assert round(d0, 3) == 0.722 and round(d1, 3) == 0.138
    # the metric egobench reports (non-spatial mean) is within 1e-4 of the spatial one here, and symmetric
    assert lpips_alex(p0, ref) == pytest.approx(d0, abs=1e-4) and lpips_alex(ref, p0) == pytest.approx(d0, abs=1e-4)
    assert lpips_alex(ref, ref) == 0.0
