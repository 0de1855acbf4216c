"""`egobench export` (INRIA 3DGS PLY) and `egobench render` (fly-through video): the format against
the reference layout, round trips through an independent reader (plyfile), and the video's frames."""

from __future__ import annotations

import numpy as np
import pytest
import torch

plyfile = pytest.importorskip("plyfile")

#: graphdeco-inria/gaussian-splatting GaussianModel.construct_list_of_attributes for SH degree 3
#: (features_dc [N, 1, 3], features_rest [N, 15, 3], scaling [N, 3], rotation [N, 4]).
INRIA_DEGREE3 = (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)]
                 + [f"f_rest_{i}" for i in range(45)] + ["opacity"] + [f"scale_{i}" for i in range(3)]
                 + [f"rot_{i}" for i in range(4)])


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A plane recording and short trained runs of a scene-gamma, a linear-colour and a 2DGS method."""
    from dataclasses import replace

    from egobench.sim.plane import plane_recording
    from egobench.train.config import preset_config
    from egobench.train.loop import train

    root = tmp_path_factory.mktemp("export")
    rec = plane_recording(root / "rec", size=24, n_frames=9, n_points=600)
    out = {}
    for method in ("ours", "no_scene_gamma", "ours_2dgs"):
        config = replace(preset_config("cpu").scaled_to(120), seed=0)
        train(rec, method, config, root / method, progress=False)
        out[method] = root / method
    return rec, out


def _from_plyfile(path, n_scales):
    """Gaussians rebuilt from plyfile's arrays (independent of egobench.export.ply.read_ply)."""
    from egobench.render.types import Gaussians

    v = plyfile.PlyData.read(str(path))["vertex"]
    col = lambda *names: torch.from_numpy(np.stack([np.asarray(v[n], np.float32) for n in names], 1))  # noqa: E731
    scales = col(*[f"scale_{i}" for i in range(n_scales)])
    if n_scales == 2:
        scales = torch.cat([scales, torch.zeros(len(scales), 1)], 1)
    return Gaussians(means=col("x", "y", "z"), quats=col("rot_0", "rot_1", "rot_2", "rot_3"), log_scales=scales,
                     opacity_logits=col("opacity")[:, 0], colors=0.5 + 0.28209479177387814 * col("f_dc_0", "f_dc_1", "f_dc_2"))


def _render(g, rec, mode):
    from egobench.render import render

    f = rec.frames[4]
    return render(g, rec.camera, f.T_world_camera.float()[None], mode=mode, background=torch.zeros(3),
                  backend="torch", want_normal=mode == "2dgs").rgb[0]


@pytest.mark.parametrize("method, mode", [("ours", "3dgs"), ("ours_2dgs", "2dgs")])
def test_export_is_the_inria_layout_and_renders_as_the_run_at_the_reference_exposure(runs, tmp_path, method, mode):
    from egobench.export.ply import export_run, ply_properties
    from egobench.model.methods import get_method
    from egobench.model.predict import formation_model, predict_image
    from egobench.train.checkpoint import load_trained_run

    rec, run_dirs = runs
    path = tmp_path / "out.ply"
    info = export_run(run_dirs[method], path)
    data = plyfile.PlyData.read(str(path))
    assert data.byte_order == "<" and [e.name for e in data.elements] == ["vertex"]
    names = [p.name for p in data["vertex"].properties]
    n_scales = 2 if mode == "2dgs" else 3
    # INRIA's order (2DGS: two scales, as hbb1/2d-gaussian-splatting writes its surfels), SH degree 0
    assert names == [n for n in INRIA_DEGREE3 if not n.startswith("f_rest") and n != f"scale_{n_scales}"][:len(names)]
    assert names == ply_properties(mode) and all(p.val_dtype == "f4" for p in data["vertex"].properties)
    run = load_trained_run(run_dirs[method], "cpu", "test")
    assert info["gaussians"] == len(run.gaussians) == data["vertex"].count
    rot = np.stack([data["vertex"][f"rot_{i}"] for i in range(4)], 1)
    np.testing.assert_allclose(np.linalg.norm(rot, axis=1), 1.0, atol=1e-6)
    # what a viewer shows (c = 0.5 + C0 f_dc, composited) is the run's image at k = 1 without vignette
    spec = get_method(method)
    ones = torch.ones(rec.camera.height, rec.camera.width)
    expected = predict_image(_render(run.gaussians, rec, mode), spec, 1.0, ones, formation_model(spec))
    shown = _render(_from_plyfile(path, n_scales), rec, mode).clamp(0, 1)
    assert float((expected - shown).abs().max()) < 2e-5


def test_linear_scene_colour_is_exported_through_the_response_per_gaussian(runs, tmp_path):
    """w/o scene gamma composites linear colour and encodes after; the PLY encodes each Gaussian.
    Only approximate: encode(sum a_i c_i) != sum a_i encode(c_i) wherever Gaussians overlap or an edge
    is semi-transparent. Measured on this short run (120 iterations, median alpha 0.95): a mean
    error of 0.049 of the display range (0.026 where alpha > 0.99), against 0.21 for the linear
    colours exported unconverted."""
    from egobench.export.ply import export_run
    from egobench.model.methods import get_method
    from egobench.model.predict import formation_model, predict_image
    from egobench.train.checkpoint import load_trained_run

    rec, run_dirs = runs
    export_run(run_dirs["no_scene_gamma"], tmp_path / "lin.ply")
    run = load_trained_run(run_dirs["no_scene_gamma"], "cpu", "test")
    spec = get_method("no_scene_gamma")
    ones = torch.ones(rec.camera.height, rec.camera.width)
    expected = predict_image(_render(run.gaussians, rec, "3dgs"), spec, 1.0, ones, formation_model(spec))
    shown = _render(_from_plyfile(tmp_path / "lin.ply", 3), rec, "3dgs").clamp(0, 1)
    raw = _render(run.gaussians, rec, "3dgs").clamp(0, 1)
    err, err_raw = float((expected - shown).abs().mean()), float((expected - raw).abs().mean())
    assert 0 < err < err_raw / 3, (err, err_raw)


def test_read_ply_takes_an_inria_degree3_file(tmp_path):
    """A PLY written the way the INRIA exporter does (SH degree 3: features transposed then
    flattened, zero normals) reads back to its positions, DC colour, opacity, scales and rotations."""
    from egobench.export.ply import SH_C0, read_ply

    rng = np.random.default_rng(3)
    n = 7
    xyz, dc, rest = rng.normal(size=(n, 3)), rng.normal(size=(n, 1, 3)), rng.normal(size=(n, 15, 3))
    opacity, scale, rot = rng.normal(size=(n, 1)), rng.normal(size=(n, 3)), rng.normal(size=(n, 4))
    attrs = np.concatenate([xyz, np.zeros_like(xyz), dc.transpose(0, 2, 1).reshape(n, -1),
                            rest.transpose(0, 2, 1).reshape(n, -1), opacity, scale, rot], axis=1)
    elements = np.empty(n, dtype=[(a, "f4") for a in INRIA_DEGREE3])
    elements[:] = list(map(tuple, attrs))
    plyfile.PlyData([plyfile.PlyElement.describe(elements, "vertex")]).write(str(tmp_path / "inria.ply"))
    g, mode = read_ply(tmp_path / "inria.ply")
    f32 = lambda a: torch.from_numpy(a.astype(np.float32))  # noqa: E731
    assert mode == "3dgs"
    torch.testing.assert_close(g.means, f32(xyz), rtol=0, atol=0)
    torch.testing.assert_close(g.colors, 0.5 + SH_C0 * f32(dc[:, 0]), rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(g.opacity_logits, f32(opacity[:, 0]), rtol=0, atol=0)
    torch.testing.assert_close(g.log_scales, f32(scale), rtol=0, atol=0)
    torch.testing.assert_close(g.quats, f32(rot), rtol=0, atol=0)


def test_read_ply_names_a_truncated_file(tmp_path, runs):
    from egobench.export.ply import export_run, read_ply

    export_run(runs[1]["ours"], tmp_path / "a.ply")
    data = (tmp_path / "a.ply").read_bytes()
    (tmp_path / "b.ply").write_bytes(data[: len(data) - 40])
    with pytest.raises(ValueError, match=r"b\.ply: not an INRIA 3DGS PLY .* or truncated"):
        read_ply(tmp_path / "b.ply")


def test_video_frames_panels_and_content(runs, tmp_path):
    import cv2

    from egobench.export.video import LABEL_PX, render_video
    from egobench.metrics import psnr
    from egobench.model.predict import formation_model, method_normaliser, predict_frame, run_maps, RenderSettings
    from egobench.train.checkpoint import load_trained_run

    rec, run_dirs = runs
    out = render_video(run_dirs["ours"], rec, tmp_path / "v.mp4", compare=run_dirs["no_scene_gamma"], captured=True,
                       every=2, max_frames=3, fps=5, progress=False)
    scale = 11  # ceil(256 / 24)
    assert out["frames"] == 3 and (out["width"], out["height"]) == (3 * 24 * scale, LABEL_PX + 24 * scale)
    cap = cv2.VideoCapture(str(tmp_path / "v.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 3
    ok, first = cap.read()
    assert ok
    run = load_trained_run(run_dirs["ours"], "cpu", "test")
    f = rec.frames[0]
    pred = predict_frame(run.gaussians, rec, f, run.spec, run.camera, run_maps(rec, run),
                         method_normaliser(rec, run.spec)[f.index], 1, RenderSettings.of(run.config),
                         formation_model(run.spec)).image
    left = cv2.cvtColor(first, cv2.COLOR_BGR2RGB)[LABEL_PX:, : 24 * scale]
    left = torch.from_numpy(cv2.resize(left, (24, 24), interpolation=cv2.INTER_AREA)).float() / 255.0
    assert psnr(left, pred, torch.ones(24, 24, dtype=torch.bool)) > 28.0
    right = cv2.cvtColor(first, cv2.COLOR_BGR2RGB)[LABEL_PX:, 2 * 24 * scale:]
    right = torch.from_numpy(cv2.resize(right, (24, 24), interpolation=cv2.INTER_AREA)).float() / 255.0
    assert psnr(right, rec.load_image(f), torch.ones(24, 24, dtype=torch.bool)) > 28.0
    with pytest.raises(ValueError, match=r"expected a \.mp4 file"):
        render_video(run_dirs["ours"], rec, tmp_path / "v.avi", progress=False)
