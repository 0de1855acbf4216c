"""`egobench export RUN --ply OUT.ply`: a trained run as the INRIA 3DGS PLY that viewers open.

Layout (graphdeco-inria/gaussian-splatting ``GaussianModel.save_ply``; 2DGS as hbb1/2d-gaussian-splatting
writes its surfels): one ``vertex`` element, binary little endian, float32 properties in this order::

    x y z  nx ny nz (zeros)  f_dc_0..2  f_rest_* (none: egobench colours have no view dependence,
    SH degree 0)  opacity (logit)  scale_0..2 (log std, metres; 2DGS: scale_0..1)  rot_0..3 (w x y z, unit)

Colours (``f_dc = (c - 0.5) / C0``, C0 = 0.2820948, so a viewer shows ``c``): the display colour
the run predicts at the recording's median exposure x gain (k = 1) without lens shading. For the
methods with scene gamma (the paper's 'ours' and its rows) and the methods without a formation
model, that is the trained colour itself and a viewer's render equals egobench's (k = 1, no
vignette). For linear scene colour (w/o scene gamma) the camera response is applied per Gaussian,
which equals the model's render only where one opaque Gaussian covers a pixel (the model composites
in linear, then encodes): tests/export/test_export.py measures a mean error of 0.05 of the display range on
a short run (0.21 without the conversion).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from egobench.io_utils import atomic_path, holding_run_folder
from egobench.model.predict import formation_model
from egobench.render.torch_backend import NEAR_PLANE, VIEWER_NEAR_PLANE
from egobench.render.types import Gaussians
from egobench.train.checkpoint import load_trained_run

SH_C0 = 0.28209479177387814


def ply_properties(mode: str = "3dgs", n_rest: int = 0) -> list[str]:
    """The INRIA vertex properties in order (2DGS surfels carry two scales)."""
    n_scales = 2 if mode == "2dgs" else 3
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(n_rest)]
            + ["opacity"] + [f"scale_{i}" for i in range(n_scales)] + ["rot_0", "rot_1", "rot_2", "rot_3"])


def display_colours(colors: Tensor, spec) -> tuple[Tensor, str]:
    """[N, 3] scene colours -> (display colours at k = 1 without shading, what they mean)."""
    if not spec.formation:
        return colors, "the trained colour (no image formation model)"
    if spec.scene_gamma:
        return colors, "display colour at the median exposure x gain (scene gamma: the trained colour itself)"
    shown = formation_model(spec).response.encode(colors.clamp(min=0.0))
    return shown, "display colour at the median exposure x gain (linear scene colour, response applied per Gaussian)"


def write_ply(path: str | Path, gaussians, mode: str, colours: Tensor, comments: list[str] = ()) -> int:
    """Write ``gaussians`` (`Gaussians`) with display ``colours`` [N, 3] as an INRIA PLY, atomically.
    Returns the number of Gaussians."""
    g = gaussians.detach().to("cpu")
    n = len(g)
    quats = g.quats / g.quats.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    n_scales = 2 if mode == "2dgs" else 3
    columns = [g.means, torch.zeros(n, 3), (colours.detach().cpu() - 0.5) / SH_C0, g.opacity_logits[:, None],
               g.log_scales[:, :n_scales], quats]
    data = torch.cat([c.to(torch.float32) for c in columns], dim=1).numpy().astype("<f4")
    props = ply_properties(mode)
    assert data.shape[1] == len(props)
    header = ["ply", "format binary_little_endian 1.0", *[f"comment {c}" for c in comments],
              f"element vertex {n}", *[f"property float {p}" for p in props], "end_header"]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            fh.write(np.ascontiguousarray(data).tobytes())
    return n


def read_ply(path: str | Path):
    """An INRIA 3DGS (or 2DGS) PLY -> (`Gaussians` with colours ``0.5 + C0 f_dc``, mode). Binary little
    endian float properties only; ValueError names the file and what differs."""
    path = Path(path)
    with open(path, "rb") as fh:
        lines = []
        while not lines or lines[-1] != "end_header":
            raw = fh.readline()
            if not raw:
                raise ValueError(f"{path}: not a PLY file (no end_header)")
            lines.append(raw.decode("ascii", "replace").strip())
        body = fh.read()
    if lines[0] != "ply" or "format binary_little_endian 1.0" not in lines:
        raise ValueError(f"{path}: expected a binary little endian PLY, got header {lines[:2]}")
    vertex = [ln.split() for ln in lines if ln.startswith("element vertex")]
    props = [ln.split() for ln in lines if ln.startswith("property")]
    if len(vertex) != 1 or any(p[:2] != ["property", "float"] for p in props):
        raise ValueError(f"{path}: expected one vertex element of float properties")
    names, n = [p[2] for p in props], int(vertex[0][2])
    missing = [k for k in ply_properties("2dgs") if k not in names]
    if missing or len(body) < 4 * n * len(names):
        raise ValueError(f"{path}: not an INRIA 3DGS PLY (missing properties {missing}) or truncated "
                         f"({len(body)} bytes of data for {n} vertices x {len(names)} floats)")
    arr = np.frombuffer(body, dtype="<f4", count=n * len(names)).reshape(n, len(names))
    col = {name: torch.from_numpy(arr[:, i].copy()) for i, name in enumerate(names)}
    scales = [col[k] for k in ("scale_0", "scale_1", "scale_2") if k in col]
    mode = "2dgs" if len(scales) == 2 else "3dgs"
    if len(scales) == 2:  # a surfel's third axis: egobench ignores it in 2DGS mode
        scales.append(torch.full_like(scales[0], -10.0))
    stack = lambda keys: torch.stack([col[k] for k in keys], dim=1)  # noqa: E731
    g = Gaussians(means=stack(["x", "y", "z"]), quats=stack(["rot_0", "rot_1", "rot_2", "rot_3"]),
                  log_scales=torch.stack(scales, dim=1), opacity_logits=col["opacity"],
                  colors=0.5 + SH_C0 * stack(["f_dc_0", "f_dc_1", "f_dc_2"]))
    return g, mode


@holding_run_folder("export", "run_dir", exclusive=False)
def export_run(run_dir: str | Path, out: str | Path) -> dict:
    """Export a trained run's Gaussians to ``out`` (INRIA PLY); returns what was written."""
    run = load_trained_run(run_dir, "cpu", f"export {run_dir}")
    colours, meaning = display_colours(run.gaussians.colors, run.spec)
    comments = [f"egobench run {Path(run_dir).name}: method {run.spec.name}, iteration {run.checkpoint['iteration']}",
                f"colours: {meaning}", "axes: world frame of the recording (metres), cameras OpenCV",
                f"near plane: egobench renders from {NEAR_PLANE} m (gsplat's); INRIA-style viewers clip below "
                f"{VIEWER_NEAR_PLANE} m and hide the Gaussians between"]
    n = write_ply(out, run.gaussians, run.spec.splat_mode, colours, comments)
    return {"path": str(out), "gaussians": n, "mode": run.spec.splat_mode, "colours": meaning}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="run folder with checkpoint.pt")
    parser.add_argument("--ply", required=True, metavar="OUT.ply", help="where to write the INRIA 3DGS PLY")


def run(args: argparse.Namespace) -> int:
    out = export_run(args.run, args.ply)
    print(f"exported {out['gaussians']} {out['mode']} Gaussians -> {out['path']} (colours: {out['colours']})")
    return 0
