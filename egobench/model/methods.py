"""Method registry: one `MethodSpec` per row of the paper's tables.

A method is a set of switches read by the one trainer (`egobench.train`) and the one
evaluator (`egobench.evaluate`); there is never a copy of the trainer per method.

Scene-colour spaces (what `Gaussians.colors` hold, see docs/paper-notes.md §2):
- ``scene_gamma=True`` (ours): colours are gamma-compressed irradiance; the formation model
  predicts ``encode(decode(x) * k * V)``.
- ``scene_gamma=False`` ("w/o scene gamma"): colours are linear radiance; the formation
  predicts ``encode(x * k * V)``. The authors' released code cannot run this ablation (it calls
  a function that does not exist), so this is egobench's own, clean definition.
- ``formation=False`` (splatfacto): colours are fitted directly to the captured (encoded) pixels,
  no exposure/gain normalisation, no vignette, no response curve.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal

MotionSampling = Literal["adaptive", "centre", "velocity_shift"]


@dataclass(frozen=True)
class MethodSpec:
    """The switches that define one reconstruction method (one table row)."""

    name: str  # registry key, e.g. "ours"
    label: str  # row label exactly as in the paper's tables, e.g. "w/o VIBA"
    calibration: Literal["online", "factory"]  # which rectified stream to train/evaluate on (online = VIBA)
    formation: bool  # model exposure*gain normalisation, vignette and response (False: fit colours directly)
    response_gamma: float  # camera response phi = gamma curve with this exponent (paper: 2.2); unused if not formation
    scene_gamma: bool  # Gaussian colours gamma-compressed (True) or linear radiance (False)
    motion_sampling: MotionSampling  # rolling-shutter model: per-pixel trajectory poses, centre-row pose, or velocity shift
    splat_mode: Literal["3dgs", "2dgs"]  # rasterized primitive
    pose_optimisation: bool  # jointly optimise per-frame pose corrections (and velocities for velocity_shift)
    n_exposure_samples: int = 1  # poses averaged over the exposure interval (blur); released code uses 1
    tables: tuple[str, ...] = ()  # which paper tables carry this row: "aria", "dtc", "quest3"
    table_labels: tuple[tuple[str, str], ...] = ()  # (table, label) where a table spells the row differently
    description: str = ""  # one sentence for reports

    @property
    def render_exposure_samples(self) -> int:
        """Poses averaged over the exposure when rendering a frame after warm-up: the velocity-shift
        model's ``n_exposure_samples``; the trajectory-sampling methods render 1."""
        return int(self.n_exposure_samples) if self.motion_sampling == "velocity_shift" else 1

    def __post_init__(self) -> None:
        if self.calibration not in ("online", "factory"):
            raise ValueError(f"MethodSpec {self.name}: calibration must be 'online' or 'factory', got {self.calibration!r}")
        if self.motion_sampling not in ("adaptive", "centre", "velocity_shift"):
            raise ValueError(
                f"MethodSpec {self.name}: motion_sampling must be adaptive|centre|velocity_shift, got {self.motion_sampling!r}"
            )
        if self.splat_mode not in ("3dgs", "2dgs"):
            raise ValueError(f"MethodSpec {self.name}: splat_mode must be '3dgs' or '2dgs', got {self.splat_mode!r}")
        if int(self.n_exposure_samples) != self.n_exposure_samples or self.n_exposure_samples < 1:
            raise ValueError(f"MethodSpec {self.name}: n_exposure_samples must be an integer >= 1, got {self.n_exposure_samples}")

    @property
    def models_rolling_shutter(self) -> bool:
        """Whether the method renders more than the centre-row pose (always so at evaluation)."""
        return self.motion_sampling != "centre"

    def label_for(self, table: str) -> str:
        """The row label in ``table`` ("aria", "dtc", "quest3"), as printed in the paper."""
        return dict(self.table_labels).get(table, self.label)

    def to_dict(self) -> dict:
        return asdict(self)


_ARIA_DTC_QUEST = ("aria", "dtc", "quest3")

METHODS: dict[str, MethodSpec] = {
    m.name: m
    for m in [
        MethodSpec(
            name="ours", label="Our Egocentric-GS", calibration="online", formation=True, response_gamma=2.2,
            scene_gamma=True, motion_sampling="adaptive", splat_mode="3dgs", pose_optimisation=False,
            tables=_ARIA_DTC_QUEST, table_labels=(("dtc", "Ours (3D-GS)"), ("quest3", "Ours (3D-GS)")),
            description="VIBA calibration, adaptive rolling-shutter motion sampling, exposure/gain/vignette/response, scene gamma",
        ),
        MethodSpec(
            name="no_viba", label="w/o VIBA", calibration="factory", formation=True, response_gamma=2.2,
            scene_gamma=True, motion_sampling="adaptive", splat_mode="3dgs", pose_optimisation=False,
            tables=_ARIA_DTC_QUEST, description="ours with the factory calibration (whole pipeline)",
        ),
        MethodSpec(
            name="no_motion_sampling", label="w/o motion sampling", calibration="online", formation=True,
            response_gamma=2.2, scene_gamma=True, motion_sampling="centre", splat_mode="3dgs",
            pose_optimisation=False, tables=_ARIA_DTC_QUEST,
            description="ours with one centre-row pose per image",
        ),
        MethodSpec(
            name="no_scene_gamma", label="w/o scene gamma", calibration="online", formation=True,
            response_gamma=2.2, scene_gamma=False, motion_sampling="adaptive", splat_mode="3dgs",
            pose_optimisation=False, tables=("aria", "dtc"),
            description="ours with linear-radiance colours: prediction encode(x*k*V) (not runnable in the authors' code)",
        ),
        MethodSpec(
            name="splatfacto", label="splatfacto", calibration="factory", formation=False, response_gamma=2.2,
            scene_gamma=True, motion_sampling="centre", splat_mode="3dgs", pose_optimisation=False,
            tables=("aria", "dtc"),
            description="vanilla 3DGS: factory calibration, centre-row poses, colours fitted directly",
        ),
        MethodSpec(
            name="on_the_move", label="3DGS-on-move", calibration="factory", formation=False, response_gamma=2.2,
            scene_gamma=True, motion_sampling="velocity_shift", splat_mode="3dgs", pose_optimisation=True,
            n_exposure_samples=2, tables=("aria",),
            description=(
                "3DGS-on-the-move style: factory calibration, per-frame linear/angular velocity from the trajectory, "
                "rolling shutter with row time linear in the rectified image (pinhole assumption) plus exposure blur, "
                "joint optimisation of pose corrections and velocities"
            ),
        ),
        MethodSpec(
            name="ours_2dgs", label="Ours 2D-GS", calibration="online", formation=True, response_gamma=2.2,
            scene_gamma=True, motion_sampling="adaptive", splat_mode="2dgs", pose_optimisation=False,
            tables=("dtc",), description="ours with 2D Gaussian surfels",
        ),
        MethodSpec(
            name="2dgs_no_motion_sampling", label="2DGS w/o motion sampling", calibration="online", formation=True,
            response_gamma=2.2, scene_gamma=True, motion_sampling="centre", splat_mode="2dgs",
            pose_optimisation=False, tables=("dtc",), table_labels=(("dtc", "w/o motion sampling"),),
            description="ours (2DGS) with centre-row poses",
        ),
    ]
}


def get_method(name: str) -> MethodSpec:
    """The registered method ``name``; ValueError listing the known names otherwise."""
    if name not in METHODS:
        raise ValueError(f"method: unknown method {name!r}; expected one of {', '.join(METHODS)}")
    return METHODS[name]
