"""Real data: the Aria Digital Twin pair (real video.vrs vs the twin's synthetic_video.vrs).

The twin's simulated RGB frames are treated as scene radiance passed through egobench's
formation model (gamma 2.2 decode, per-frame exposure x gain of the real frame relative to the
twin's own, no lens shading, no white balance, no noise); the real frames are the measurement.
Frames are paired by timestamp (the twin renders the same moments, within ~0.1 ms), both in the
raw 1408 px fisheye camera, and area-downsampled by ``downsample`` for speed. With only three
frames nothing is held out: every statistic is fitted on the even-checkerboard pixels and the
gain scored on the odd ones. Geometric causes are not tested (same calibration and poses; no
per-pixel image velocity is derived for the twin), distortion is not tested (raw fisheye images).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from egobench.diagnose.core import DiagnosisConfig, diagnose_residuals
from egobench.diagnose.report import save_png, write_report
from egobench.effects import EFFECTS
from egobench.residual.signatures import DiagnosisContext, decode, encode
from egobench.sim import motion_stats

RGB_STREAM = "214-1"
#: Causes testable on the ADT pair (see module docstring).
ADT_CAUSES = tuple(name for name, e in EFFECTS.items() if e.on_adt)


def read_rgb_frames(vrs_path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
    """-> (images [N, H, W, 3] uint8, t_ns [N], exposure_s [N], gain [N], calibration dict) of the RGB stream."""
    from projectaria_tools.core import data_provider
    from projectaria_tools.core.stream_id import StreamId

    path = Path(vrs_path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: VRS file not found")
    provider = data_provider.create_vrs_data_provider(str(path))
    if provider is None:
        raise ValueError(f"{path}: projectaria_tools could not open the VRS file")
    sid = StreamId(RGB_STREAM)
    n = provider.get_num_data(sid)
    if n == 0:
        raise ValueError(f"{path}: no frames in the RGB stream {RGB_STREAM}")
    imgs, ts, exp, gain = [], [], [], []
    for i in range(n):
        img, rec = provider.get_image_data_by_index(sid, i)
        imgs.append(img.to_numpy_array())
        ts.append(rec.capture_timestamp_ns)
        exp.append(rec.exposure_duration)
        gain.append(rec.gain)
    cal = {}
    try:
        c = provider.get_device_calibration().get_camera_calib("camera-rgb")
        get = getattr(c, "get_projection_params", None) or c.projection_params
        p = np.asarray(get(), dtype=np.float64)
        w, h = c.get_image_size()
        cal = {"params": p.tolist(), "width": int(w), "height": int(h)}
    except Exception:  # calibration is optional for the diagnosis (falls back to the image centre)
        cal = {}
    return np.stack(imgs), np.asarray(ts, dtype=np.int64), np.asarray(exp, float), np.asarray(gain, float), cal


def _area_down(img: np.ndarray, factor: int) -> np.ndarray:
    H, W = img.shape[:2]
    return cv2.resize(img, (W // factor, H // factor), interpolation=cv2.INTER_AREA)


def adt_pair(adt_dir: str | Path, downsample: int = 8, gamma: float = 2.2):
    """-> (measured [F, h, w, 3], predicted [F, h, w, 3], DiagnosisContext, info dict)."""
    adt_dir = Path(adt_dir)
    real, t_real, e_real, g_real, cal = read_rgb_frames(adt_dir / "video.vrs")
    syn, t_syn, e_syn, g_syn, _ = read_rgb_frames(adt_dir / "synthetic_video.vrs")
    pairs = []
    for i, t in enumerate(t_real):  # nearest twin frame in time
        j = int(np.argmin(np.abs(t_syn - t)))
        if abs(int(t_syn[j]) - int(t)) < 5_000_000:
            pairs.append((i, j, int(t_syn[j]) - int(t)))
    if len(pairs) < 3:
        raise ValueError(f"{adt_dir}: fewer than 3 real/twin frame pairs within 5 ms ({len(pairs)})")
    meas = np.stack([_area_down(real[i], downsample) for i, _, _ in pairs]).astype(np.float64) / 255.0
    syn_d = np.stack([_area_down(syn[j], downsample) for _, j, _ in pairs]).astype(np.float64) / 255.0
    # twin radiance (linear, relative) re-exposed with each real frame's exposure x gain
    k = np.array([e_real[i] * g_real[i] / (e_syn[j] * g_syn[j]) for i, j, _ in pairs])
    k = k / np.median(k)
    lin = decode(syn_d, gamma) * k[:, None, None, None]
    pred = np.clip(encode(lin, gamma), 0.0, 1.0)
    F, H, W, _ = meas.shape
    if cal:
        f = cal["params"][0] * W / cal["width"]
        cx = (cal["params"][1] + 0.5) * W / cal["width"] - 0.5
        cy = (cal["params"][2] + 0.5) * H / cal["height"] - 0.5
    else:
        f, cx, cy = 0.43 * W, (W - 1) / 2, (H - 1) / 2
    v, u = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    # valid: inside the image circle where the twin rendered something in every frame
    rendered = (syn_d.max(axis=-1) > 2.0 / 255).all(axis=0)
    radius = np.hypot(u - cx, v - cy)
    valid = rendered & (radius < 0.48 * min(H, W))
    ctx = DiagnosisContext(
        frame_index=np.arange(1, F + 1), exposure_s=np.array([e_real[i] for i, _, _ in pairs]),
        gain=np.array([g_real[i] for i, _, _ in pairs]), valid=valid, row_time_ratio=v / (H - 1.0),
        principal_point=(float(cx), float(cy)), focal_px=float(f), readout_s=0.0, pixel_velocity_px_s=None,
        gamma_assumed=gamma, noise_shot=None, noise_read=None,
        meta={"source": "ADT twin (synthetic_video.vrs) as scene radiance vs real video.vrs",
              "downsample": downsample},
    )
    info = {"pairs": [{"real": i, "twin": j, "dt_ns": dt} for i, j, dt in pairs],
            "real_exposure_s": [float(e_real[i]) for i, _, _ in pairs], "real_gain": [float(g_real[i]) for i, _, _ in pairs],
            "twin_exposure_s": [float(e_syn[j]) for _, j, _ in pairs], "twin_gain": [float(g_syn[j]) for _, j, _ in pairs],
            "image_size": [W, H], "valid_fraction": float(valid.mean())}
    return meas, pred, ctx, info


def motion_comparison(real_trajectory: str | Path | None) -> dict:
    """Simulated vs real head-motion statistics via egobench.sim.motion_stats (with a real trajectory)."""
    if real_trajectory is None:
        return {"note": "no real trajectory given (--real-trajectory)"}
    try:
        rows = motion_stats.compare(str(real_trajectory), kind="indoor", seeds=[0, 1], duration_s=10.0)
    except Exception as exc:  # report, do not fail the diagnosis
        return {"note": f"egobench.sim.motion_stats.compare failed: {exc}"}
    return {"rows": rows, "table": motion_stats.format_table(rows)}


def diagnose_adt(adt_dir: str | Path, out_dir: str | Path, config: DiagnosisConfig | None = None,
                 downsample: int = 8, real_trajectory: str | Path | None = None) -> dict:
    """Diagnose the twin against the real frames; write the report into out_dir; return the JSON record."""
    meas, pred, ctx, info = adt_pair(adt_dir, downsample)
    cfg = replace(config or DiagnosisConfig(), causes=ADT_CAUSES, max_causes=len(ADT_CAUSES))
    d = diagnose_residuals(meas, pred, ctx, cfg)
    info["unmodelled_content_fraction"] = d.unmodelled_fraction
    info["head_motion"] = motion_comparison(real_trajectory)
    record = write_report(out_dir, d, meas, pred, title="ADT: what the digital twin's simulation gets wrong",
                          extra=info)
    if d.unmodelled_map is not None:
        _unmodelled_figure(Path(out_dir) / "figures" / "unmodelled_content.png", meas, d.unmodelled_map)
    return record


def _unmodelled_figure(path: Path, measured: np.ndarray, trimmed: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = trimmed.shape[0]
    fig, axes = plt.subplots(1, n, figsize=(3 * n, 3), squeeze=False)
    for i in range(n):
        ax = axes[0, i]
        ax.imshow(np.clip(measured[min(i, measured.shape[0] - 1)], 0, 1))
        H, W = measured.shape[1:3]
        ax.imshow(trimmed[i], cmap="Reds", alpha=0.45, extent=(0, W, H, 0), vmin=0, vmax=1)
        ax.set_title("off-model cells (red)", fontsize=8)
        ax.axis("off")
    save_png(fig, path)
