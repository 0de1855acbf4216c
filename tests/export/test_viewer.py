"""`egobench view`: the page holds the run and nothing from outside, and in a real browser (headless Chromium)
it shows what egobench renders at a camera, through the formation model's exposure and response."""

from __future__ import annotations

import base64
import json
import math
import re
from dataclasses import replace

import numpy as np
import pytest
import torch

from egobench.export.browser import browser_missing, canvas_pixels, open_page
from egobench.export.viewer import PAGE, open_run, reference_view, write_view
from egobench.render.torch_backend import NEAR_PLANE, quat_to_rotmat
from egobench.sim.plane import plane_recording
from egobench.train.checkpoint import read_run_checkpoint
from egobench.train.config import preset_config
from egobench.train.loop import train

#: the page must match egobench's render of the same camera at least this well (8-bit PSNR, dB)
MIN_PSNR_DB = 30.0


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A simulated plane recording, 'ours' and w/o motion sampling trained on it, and the page of both."""
    root = tmp_path_factory.mktemp("viewer")
    rec = plane_recording(root / "rec", size=32, n_frames=9, n_points=600)
    runs = {}
    for method in ("ours", "no_motion_sampling", "ours_2dgs"):
        train(rec, method, replace(preset_config("cpu").scaled_to(150), seed=0), root / method, progress=False)
        runs[method] = root / method
    out = write_view(runs["ours"], rec, root / "view", compare=runs["no_motion_sampling"])
    return rec, runs, root / "view" / PAGE, out


def _payload(page_path) -> dict:
    text = page_path.read_text()
    return json.loads(text.split('<script id="egobench-data" type="application/json">', 1)[1].split("</script>", 1)[0])


def _floats(b64: str) -> np.ndarray:
    return np.frombuffer(base64.b64decode(b64), dtype="<f4")


def test_the_page_holds_the_run_and_every_camera(scene):
    rec, runs, page, out = scene
    data = _payload(page)
    ck = read_run_checkpoint(runs["ours"] / "checkpoint.pt")
    p = ck["params"]
    n = len(p["means"])
    assert out["gaussians"][0] == n and data["runs"][0]["n"] == n and data["near"] == NEAR_PLANE
    np.testing.assert_array_equal(_floats(data["runs"][0]["means"]).reshape(n, 3), p["means"].numpy())
    # the world covariances: R diag(s^2) R^T of the checkpoint's quaternions and log scales
    R = quat_to_rotmat(p["quats"].double())
    cov = R @ torch.diag_embed(torch.exp(2 * p["scales"].double())) @ R.transpose(1, 2)
    six = _floats(data["runs"][0]["cov"]).reshape(n, 6)
    np.testing.assert_allclose(six[:, [0, 3, 5]], cov[:, [0, 1, 2], [0, 1, 2]].numpy(), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(six[:, 1], cov[:, 0, 1].numpy(), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(_floats(data["runs"][0]["opacity"]), torch.sigmoid(p["opacities"]).numpy(), rtol=1e-6)
    assert [f["index"] for f in data["frames"]] == [f.index for f in rec.frames]
    assert [f["index"] for f in data["frames"] if f["held_out"]] == [f.index for f in rec.test_frames]
    assert [r["method"] for r in data["runs"]] == ["ours", "no_motion_sampling"]


def test_the_page_asks_for_nothing_outside_itself(scene):
    text = scene[2].read_text()
    assert "default-src 'none'" in text  # the page's own policy: no request leaves it
    assert re.findall(r"""(?:src|href)\s*=\s*["'](?!data:)""", text) == []
    assert "http://" not in text and "https://" not in text


def test_a_2dgs_run_is_refused_with_its_method_named(scene, tmp_path):
    rec, runs, _page, _out = scene
    with pytest.raises(ValueError, match="'ours_2dgs' renders 2DGS surfels"):
        write_view(runs["ours_2dgs"], rec, tmp_path)
    assert not (tmp_path / PAGE).exists()


def test_a_run_of_another_calibration_stream_is_refused(scene, tmp_path):
    rec, runs, _page, _out = scene
    train(rec, "ours", replace(preset_config("cpu").scaled_to(20), seed=0), tmp_path / "run", progress=False)
    factory = replace(rec, calibration="factory")
    with pytest.raises(ValueError, match="renders the 'online' stream, the recording was loaded with 'factory'"):
        write_view(tmp_path / "run", factory, tmp_path / "view")


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a - b) ** 2))
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def _quantised(image: np.ndarray) -> np.ndarray:
    return np.round(np.clip(image, 0.0, 1.0) * 255.0) / 255.0


@pytest.mark.skipif(browser_missing() is not None, reason=f"no browser here: {browser_missing()}")
def test_the_page_in_headless_chromium_shows_what_egobench_renders(scene):
    rec, runs, page_path, _out = scene
    ours, other = open_run(runs["ours"], rec, "test"), open_run(runs["no_motion_sampling"], rec, "test")
    held, training = rec.test_frames[1].index, rec.train_frames[2].index
    with open_page(page_path) as (page, requests):
        measured = {}
        for frame in (held, training):
            page.evaluate(f"() => window.egobench.snap({frame})")
            measured[frame] = _psnr(canvas_pixels(page), _quantised(reference_view(ours, frame)))
        # the exposure slider: one stop more, as the formation model predicts it (k x 2), not as it was
        page.evaluate(f"() => window.egobench.snap({held})")
        page.evaluate("() => window.egobench.setExposure(1.0)")
        brighter = canvas_pixels(page)
        to_brighter = _psnr(brighter, _quantised(reference_view(ours, held, exposure_stops=1.0)))
        to_before = _psnr(brighter, _quantised(reference_view(ours, held)))
        # the response slider
        page.evaluate("() => { window.egobench.setExposure(0.0); window.egobench.setGamma(1.6); }")
        gamma = _psnr(canvas_pixels(page), _quantised(reference_view(ours, held, gamma=1.6)))
        # the second run at the same camera
        page.evaluate("() => { window.egobench.setGamma(2.2); window.egobench.setRun(1); }")
        second = _psnr(canvas_pixels(page), _quantised(reference_view(other, held)))
    assert min(measured.values()) >= MIN_PSNR_DB, measured
    assert to_brighter >= MIN_PSNR_DB and to_before < to_brighter - 10.0, (to_brighter, to_before)
    assert gamma >= MIN_PSNR_DB and second >= MIN_PSNR_DB, (gamma, second)
    assert requests == [page_path.resolve().as_uri()]  # nothing but the page itself was requested
