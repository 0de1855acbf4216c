"""How fast a misregistration costs PSNR on a real Aria frame: the measurement behind the exponent
bound of egobench.analysis.sensitivity's model (module doc).

    python scripts/misregistration_exponent.py ../shared/data/adt_sample/video.vrs

Reads the middle camera-rgb frame of the VRS (projectaria-tools), takes the luminance of its
central half (inside the fisheye circle), area-downsamples it by 1, 4 and 11 (704, 176, 64 px) and
prints the mean square of the frame minus itself shifted by δ px and the local exponent
d log MSE / d log δ between consecutive shifts.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from egobench.analysis.sensitivity import misregistration_exponents  # noqa: E402

SHIFTS_PX = (0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)


def area_down(a: np.ndarray, f: int) -> np.ndarray:
    h, w = (a.shape[0] // f) * f, (a.shape[1] // f) * f
    return a[:h, :w].reshape(h // f, f, w // f, f).mean((1, 3))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("vrs", type=Path, help="an Aria recording (.vrs) with a camera-rgb stream")
    args = parser.parse_args()
    if not args.vrs.is_file():
        raise SystemExit(f"{args.vrs}: VRS file not found")
    from projectaria_tools.core import data_provider

    provider = data_provider.create_vrs_data_provider(str(args.vrs))
    sid = provider.get_stream_id_from_label("camera-rgb")
    frame = provider.get_image_data_by_index(sid, provider.get_num_data(sid) // 2)[0].to_numpy_array()
    lum = frame.astype(np.float64).mean(-1) / 255.0 if frame.ndim == 3 else frame / 255.0
    h, w = lum.shape
    centre = lum[h // 4: 3 * h // 4, w // 4: 3 * w // 4]
    print("shift px:        " + " ".join(f"{d:>8g}" for d in SHIFTS_PX))
    for f in (1, 4, 11):
        img = area_down(centre, f)
        mse, p = misregistration_exponents(img, SHIFTS_PX)
        print(f"{img.shape[1]:>4} px MSE:     " + " ".join(f"{m:8.2e}" for m in mse))
        print(f"{img.shape[1]:>4} px exponent:     " + " ".join(f"{x:8.2f}" for x in p))
    return 0


if __name__ == "__main__":
    sys.exit(main())
