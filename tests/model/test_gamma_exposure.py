"""The compiled gamma exposure (`egobench.model.gamma_exposure`) against its oracle, the torch ops of
`FormationModel` (``clamp(encode(decode(x) * s), 0, 1)``), on every branch of the toed curve."""

import pytest
import torch

from egobench.bench import cpu_threads
from egobench.model.formation import FormationConfig, FormationModel, GammaResponse
from egobench.model.gamma_exposure import gamma_expose

RESPONSE = GammaResponse()
Y0 = RESPONSE.toe_linear ** (1 / RESPONSE.gamma)  # display value where the toe ends


def _scene(dtype, H=24, W=40, seed=0):
    """Colours over the power law, the toe (x < y0 and x * s**(1/gamma) < y0), negatives and values the
    clamp cuts; a scale with zeros (outside an image circle), small and large values."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(H, W, 3, generator=g, dtype=torch.float64) * 1.6 - 0.2
    x[:4] *= 0.02  # around y0
    x[4:6] = Y0 * (1 + torch.rand(2, W, 3, generator=g, dtype=torch.float64))  # on the law, toe after scaling
    s = torch.rand(H, W, 1, generator=g, dtype=torch.float64) * 2.0
    s[4:6] = 0.05
    s[0, :7] = 0.0
    return x.to(dtype), s.to(dtype)


def _oracle(x, s, decode, clamp):
    y = RESPONSE.encode((RESPONSE.decode(x) if decode else x) * s)
    return y.clamp(0.0, 1.0) if clamp else y


@pytest.mark.parametrize("decode", [True, False])
@pytest.mark.parametrize("clamp", [True, False])
def test_value_and_gradients_match_the_torch_ops_in_float64(decode, clamp):
    x, s = _scene(torch.float64)
    xa, sa = x.clone().requires_grad_(True), s.clone().requires_grad_(True)
    xb, sb = x.clone().requires_grad_(True), s.clone().requires_grad_(True)
    ya = gamma_expose(xa, sa, RESPONSE.gamma, RESPONSE.toe_linear, decode=decode, clamp=clamp)
    yb = _oracle(xb, sb, decode, clamp)
    w = torch.randn(ya.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    (ya * w).sum().backward()
    (yb * w).sum().backward()
    torch.testing.assert_close(ya, yb, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(xa.grad, xb.grad, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(sa.grad, sb.grad, rtol=1e-10, atol=1e-12)
    cut = (yb == 0.0) | (yb == 1.0) if clamp else (yb < 0.0) | (yb > 1.0)
    assert bool(cut.any())  # the scene reaches past [0, 1]


def test_float32_matches_to_rounding_and_broadcast_scales_reduce():
    """float32 within a few units in the last place; a scalar scale gets the summed gradient."""
    x, s = _scene(torch.float32, seed=2)
    torch.testing.assert_close(gamma_expose(x, s, 2.2, 1e-5, decode=True, clamp=True), _oracle(x, s, True, True),
                               rtol=0, atol=3e-7)
    k = torch.tensor(1.3, dtype=torch.float64, requires_grad=True)
    kb = k.detach().clone().requires_grad_(True)
    x64 = x.double()
    gamma_expose(x64, k, 2.2, 1e-5, decode=True, clamp=True).sum().backward()
    _oracle(x64, kb, True, True).sum().backward()
    assert k.grad.shape == () and abs(float(k.grad - kb.grad)) < 1e-9 * abs(float(kb.grad))


def test_gradcheck_away_from_the_branch_edges():
    g = torch.Generator().manual_seed(3)
    x = (torch.rand(5, 6, 3, generator=g, dtype=torch.float64) * 0.8 + 0.1).requires_grad_(True)
    x.data[0, 0] = 0.002  # on the toe
    s = (torch.rand(5, 6, 1, generator=g, dtype=torch.float64) + 0.5).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: gamma_expose(a, b, 2.2, 1e-5, decode=True, clamp=True), (x, s))


def test_bits_do_not_depend_on_the_thread_count():
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba's pool has one thread")
    x, s = _scene(torch.float32, H=64, W=64, seed=4)
    outs = []
    for threads in (1, 2):
        xa = x.clone().requires_grad_(True)
        with cpu_threads(threads, 1):
            y = gamma_expose(xa, s, 2.2, 1e-5, decode=True, clamp=True)
            y.backward(torch.ones_like(y))
        outs.append((y.detach(), xa.grad))
    assert torch.equal(outs[0][0], outs[1][0]) and torch.equal(outs[0][1], outs[1][1])


_POWER_LAW_SCRIPT = """
import sys, torch
from egobench.model.gamma_exposure import gamma_expose
g = torch.Generator().manual_seed(7)
x = (0.05 + 0.9 * torch.rand(32, 32, 3, generator=g)).to(torch.float32)  # on the power law after any scale below
s = (0.5 + torch.rand(32, 32, 1, generator=g)).to(torch.float32)
y = gamma_expose(x, s, 2.2, 1e-5, decode=True, clamp=False)
sys.stdout.write(y.numpy().tobytes().hex())
"""


def test_the_exposures_power_is_glibcs_rounded_and_the_same_with_numpys_avx512_paths_off():
    """On the power law the output is x * r, r = s ** (1 / gamma) in float64 (Python's math.pow: glibc, as the
    kernel) rounded to float32; and the bits do not move when numpy's AVX-512 code is off (what an AVX2-only
    machine runs): numpy's own power gave other bits there (results/cross_isa/README.md, 2026-11-29)."""
    import math
    import os
    import subprocess
    import sys

    import numpy as np

    from egobench.host import numpy_avx512_targets

    def run(extra: dict) -> str:
        return subprocess.run([sys.executable, "-c", _POWER_LAW_SCRIPT], capture_output=True, text=True, check=True,
                              env={**os.environ, **extra}).stdout

    host = run({})
    g = torch.Generator().manual_seed(7)
    x = (0.05 + 0.9 * torch.rand(32, 32, 3, generator=g)).to(torch.float32).numpy()
    s = (0.5 + torch.rand(32, 32, 1, generator=g)).to(torch.float32).numpy()
    r = np.vectorize(lambda v: np.float32(math.pow(float(v), 1 / 2.2)))(s).astype(np.float32)
    expected = (x.astype(np.float64) * r.astype(np.float64)).astype(np.float32)
    assert host == expected.tobytes().hex()
    if numpy_avx512_targets():
        assert run({"NPY_DISABLE_CPU_FEATURES": " ".join(numpy_avx512_targets())}) == host


def test_predict_takes_the_compiled_pass_for_one_cpu_image_and_torch_otherwise():
    fm = FormationModel(FormationConfig.paper_trainer())
    x, s = _scene(torch.float32, seed=5)
    vignette = s[..., 0]
    one = fm.predict(x.requires_grad_(True), scale_k=1.3, vignette=vignette)
    assert type(one.grad_fn).__name__ == "_GammaExposeCPUBackward"
    batch = fm.predict(torch.stack([x.detach(), x.detach()]), scale_k=1.3, vignette=vignette)  # [2, H, W, 3]: torch
    assert batch.grad_fn is None
    torch.testing.assert_close(batch[1], one.detach(), rtol=0, atol=3e-7)


def test_bad_input_is_named():
    x, s = _scene(torch.float32)
    with pytest.raises(ValueError, match=r"gamma_expose: expected a CPU float \[H, W, 3\] image"):
        gamma_expose(x[..., :2], s, 2.2, 1e-5, decode=True, clamp=True)
    with pytest.raises(ValueError, match=r"broadcastable to \[H, W, 1\]"):
        gamma_expose(x, s.expand(-1, -1, 3), 2.2, 1e-5, decode=True, clamp=True)
    with pytest.raises(ValueError, match="toe_linear in"):
        gamma_expose(x, s, 2.2, 0.0, decode=True, clamp=True)
