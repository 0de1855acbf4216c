"""`egobench view RUN --recording REC --out DIR`: one self-contained HTML page to look inside a trained scene.

The page (DIR/index.html) holds everything it shows, so it opens offline and sends no request: the run's
Gaussians, every frame's camera (the centre-row pose of the recording's trajectory) with its captured image
and its exposure normaliser k, the run's vignette map and its image formation. It renders the Gaussians with
WebGL2 by the same rules as egobench's rasterizers (gsplat 1.5.3: EWA projection with the 0.3 px^2 low-pass and
the 1.3 tan(fov) clamp, alpha = min(0.999, o exp(-s)) skipped below 1/255, composited in depth order over the
run's background, near plane 0.01 m) into a floating-point target, then applies the method's formation as
egobench does (`FormationModel.predict`: encode(decode(c) x k x V), clamped). It shows the captured frame and
|render - captured| beside the render, with sliders for exposure x gain (stops on top of the frame's k) and
the response gamma, a second run at the same camera (``--compare``), orbit and fly controls, and a snap to any
training or held-out camera (docs/viewer.md).

The renderer is the page's own (egobench/resources/viewer.js, ~400 lines) rather than a vendored splat
viewer: egobench's colours have no view dependence, its formation works on linear light after compositing
(a post pass on the float target), and its near plane and pixel convention differ from the INRIA-derived
viewers' (0.2 m). `reference_view` is what the page's render panel must show, computed by egobench.
"""

from __future__ import annotations

import argparse
import base64
import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import cv2
import numpy as np
import torch

import egobench.render
from egobench.data import load_recording
from egobench.data.recording import Recording
from egobench.data.reader import add_input_arguments
from egobench.io_utils import atomic_path, holding_run_folder
from egobench.model.formation import FormationConfig, FormationModel, GammaResponse
from egobench.model.predict import RenderSettings, formation_model, run_normaliser, predict_image, resize_map, run_maps
from egobench.render.torch_backend import NEAR_PLANE, quat_to_rotmat
from egobench.train.checkpoint import TrainedRun, check_run_complete, load_trained_run, recording_for_run

#: the page written into the output folder
PAGE = "index.html"
#: the captured frames are embedded as PNG (lossless: the difference panel compares pixels)
IMAGE_FORMAT = ".png"


@dataclass
class ViewRun:
    """A run set up as the page shows it: its Gaussians, formation, vignette and per-frame k."""

    run: TrainedRun
    recording: Recording
    vignette: torch.Tensor  # [H, W] at the run's camera
    k_of: dict  # frame index -> k
    settings: RenderSettings


def open_run(run_dir, recording_dir, where: str) -> ViewRun:
    """A finished 3DGS run and its recording (in the run's calibration stream) -> `ViewRun`."""
    run = load_trained_run(run_dir, "cpu", where)
    check_run_complete(run_dir, run.checkpoint)
    if run.spec.splat_mode != "3dgs":
        raise ValueError(f"{where}: method {run.spec.name!r} renders 2DGS surfels; the page renders 3DGS Gaussians "
                         "(use a 3DGS method's run, e.g. 'ours')")
    rec = recording_dir if isinstance(recording_dir, Recording) else load_recording(recording_dir, run.spec.calibration)
    if rec.calibration != run.spec.calibration:
        raise ValueError(f"{where}: method {run.spec.name!r} renders the {run.spec.calibration!r} stream, the recording "
                         f"was loaded with {rec.calibration!r} (pass the recording folder instead)")
    return ViewRun(run, rec, run_maps(rec, run).vignette, run_normaliser(rec, run),
                   RenderSettings.of(run.config, "cpu"))


def _b64(array: np.ndarray) -> str:
    """Little-endian float32 bytes of ``array`` as base64 (the page reads them into a Float32Array)."""
    return base64.b64encode(np.ascontiguousarray(array, dtype="<f4").tobytes()).decode("ascii")


def gaussians_payload(view: ViewRun) -> dict:
    """The run's Gaussians as the page reads them: means [N, 3], world covariances (xx, xy, xz, yy, yz, zz),
    opacities and colours, in float32 (the covariance from float64 products of the rotation and scales)."""
    g = view.run.gaussians
    R = quat_to_rotmat(g.quats.detach().double())
    M = R * torch.exp(g.log_scales.detach().double())[:, None, :]
    cov = M @ M.transpose(1, 2)
    six = torch.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 1], cov[:, 1, 2], cov[:, 2, 2]], -1)
    return {"label": view.run.spec.label, "method": view.run.spec.name, "n": len(g),
            "means": _b64(g.means.detach().numpy()), "cov": _b64(six.numpy()),
            "opacity": _b64(torch.sigmoid(g.opacity_logits.detach()).numpy()),
            "colors": _b64(g.colors.detach().numpy()),
            "background": [float(c) for c in view.settings.background],
            "formation": _formation_payload(view), "vignette": _b64(view.vignette.numpy()),
            "k": {str(i): float(k) for i, k in view.k_of.items()}}


def _formation_payload(view: ViewRun) -> dict:
    spec = view.run.spec
    formation = formation_model(spec)
    response, cfg = formation.response, formation.config
    if spec.formation and not isinstance(response, GammaResponse):
        raise ValueError(f"view: method {spec.name!r} uses a {type(response).__name__}; the page applies gamma responses")
    return {"enabled": bool(spec.formation), "scene_gamma": bool(spec.scene_gamma), "gamma": float(spec.response_gamma),
            "toe_linear": float(getattr(response, "toe_linear", 1e-5)), "vignette": bool(cfg.vignette),
            "exposure_gain": bool(cfg.exposure_gain), "clamp": bool(cfg.clamp)}


def _png_data_url(image: torch.Tensor) -> str:
    """[H, W, 3] float in [0, 1] -> a PNG data URL (8 bits, as captured)."""
    rgb = (image.clamp(0, 1) * 255.0).round().to(torch.uint8).numpy()
    ok, buf = cv2.imencode(IMAGE_FORMAT, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError("view: OpenCV could not encode a PNG")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def frames_payload(view: ViewRun) -> list[dict]:
    """Every frame: index, held out or not, T_world_camera (row-major, the centre-row pose) and its captured image
    at the run's camera."""
    held = {f.index for f in view.recording.test_frames}
    return [{"index": f.index, "held_out": f.index in held,
             "pose": [float(v) for v in f.T_world_camera.double().reshape(-1)],
             "image": _png_data_url(resize_map(view.recording.load_image(f), view.run.camera))}
            for f in view.recording.frames]


def page_payload(view: ViewRun, other: ViewRun | None = None) -> dict:
    cam = view.run.camera
    return {"format": "egobench-view-1", "width": cam.width, "height": cam.height,
            "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "near": NEAR_PLANE,
            "recording": str(view.recording.root), "frames": frames_payload(view),
            "runs": [gaussians_payload(v) for v in (view, other) if v is not None]}


def page_html(payload: dict) -> str:
    """The page: the template with the viewer's script and the payload inlined (no external resource)."""
    folder = resources.files("egobench") / "resources"
    template = (folder / "viewer.html").read_text(encoding="utf-8")
    script = (folder / "viewer.js").read_text(encoding="utf-8")
    data = json.dumps(payload, separators=(",", ":")).replace("</", "<\\/")
    return template.replace("/*EGOBENCH_SCRIPT*/", script).replace("/*EGOBENCH_DATA*/", data)


@holding_run_folder("view", "run_dir", exclusive=False)
def write_view(run_dir, recording_dir, out_dir, *, compare=None) -> dict:
    """Write ``out_dir``/index.html for the run in ``run_dir`` (and ``compare``) -> what was written."""
    view = open_run(run_dir, recording_dir, f"view {run_dir}")
    other = None
    if compare is not None:
        other = open_run(compare, recording_dir, f"view {compare}")  # a folder: loaded in the run's own stream
        if other.run.camera != view.run.camera:
            raise ValueError(f"view: --compare {compare} was trained at {other.run.camera.width} px, {run_dir} at "
                             f"{view.run.camera.width} px; the page shows both at one camera")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / PAGE
    with atomic_path(path) as tmp:
        Path(tmp).write_text(page_html(page_payload(view, other)), encoding="utf-8")
    return {"path": str(path), "bytes": path.stat().st_size, "frames": len(view.recording.frames),
            "runs": [view.run.spec.label] + ([other.run.spec.label] if other else []),
            "gaussians": [len(view.run.gaussians)] + ([len(other.run.gaussians)] if other else [])}


def reference_view(view: ViewRun, frame_index: int, exposure_stops: float = 0.0, gamma: float | None = None) -> np.ndarray:
    """What the page's render panel shows at frame ``frame_index``'s camera, computed by egobench -> [H, W, 3] in
    [0, 1]: the run's Gaussians at the frame's centre-row pose (no rolling-shutter or exposure samples), over the
    run's background, through the method's formation with k x 2^stops and the response ``gamma``."""
    frame = next((f for f in view.recording.frames if f.index == frame_index), None)
    if frame is None:
        raise ValueError(f"view: the recording has no frame {frame_index}")
    spec = view.run.spec
    bg = torch.tensor(view.settings.background, dtype=torch.float32)
    with torch.no_grad():
        out = egobench.render.render(view.run.gaussians, view.run.camera, frame.T_world_camera.to(torch.float32),
                                     mode="3dgs", background=bg, backend=view.settings.backend)
        rgb = out.rgb[0]
        formation = formation_model(spec) if gamma is None else FormationModel(FormationConfig.paper_trainer(gamma=gamma))
        k = view.k_of[frame.index] * (2.0 ** exposure_stops)
        return predict_image(rgb, spec, k, view.vignette, formation).numpy()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="run folder with checkpoint.pt and train.json (a finished 3DGS run)")
    parser.add_argument("--recording", required=True, help="the recording the run was trained on")
    parser.add_argument("--out", required=True, help="folder to write index.html into")
    parser.add_argument("--compare", default=None, metavar="RUN2", help="a second run to toggle to at the same camera")
    parser.add_argument("--screenshot", default=None, metavar="PNG",
                        help="also write a screenshot of the page at the first held-out camera (headless Chromium)")
    add_input_arguments(parser)


def run(args: argparse.Namespace) -> int:
    out = write_view(args.run, recording_for_run(args.run, args), args.out, compare=args.compare)
    print(f"view: {out['frames']} frames, {' | '.join(out['runs'])} ({', '.join(map(str, out['gaussians']))} Gaussians)"
          f", {out['bytes'] / 1e6:.1f} MB -> {out['path']}")
    if args.screenshot:
        from egobench.export.browser import page_screenshot  # playwright: loaded only for a screenshot

        page_screenshot(out["path"], args.screenshot)
        print(f"view: screenshot -> {args.screenshot}")
    return 0
