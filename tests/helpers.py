"""Constants and small helpers shared by several test modules."""

from __future__ import annotations

import json
from pathlib import Path

from tests.conftest import SHARED_DATA

__all__ = ["SHARED_DATA", "ARIA_RGB_PARAMS_1408", "write_records"]

#: A real Aria RGB online calibration (1408 x 1408; the first line of the MPS sample's
#: online_calibration.jsonl), so the analytic tests run without the data folder.
ARIA_RGB_PARAMS_1408 = [
    609.0993041992188, 714.49365234375, 705.4052124023438, 0.4153491258621216, -0.46660879254341125,
    0.0394107960164547, 1.304983139038086, -1.7682749032974243, 0.6525987982749939,
    7.804521010257304e-05, 0.0006019965512678027, -0.0011151430662721395, 0.0006172532448545098,
    -0.00233874237164855, 0.0016606695717200637,
]


def write_records(root: Path, recs: list[dict]) -> list[Path]:
    """Write run records as root/runNNN/eval.json; the paths deliberately do not carry the identity
    (tables and plots must read it from the records)."""
    paths = []
    for i, r in enumerate(recs):
        p = root / f"run{i:03d}" / "eval.json"
        p.parent.mkdir(parents=True)
        p.write_text(json.dumps(r))
        paths.append(p)
    return paths
