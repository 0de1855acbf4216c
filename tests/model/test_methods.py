"""The method registry: every paper row present, each with the switches the paper describes."""

from __future__ import annotations

import pytest

from egobench.model.methods import METHODS, MethodSpec, get_method

EXPECTED = {
    # name: (calibration, formation, scene_gamma, motion_sampling, splat_mode, pose_optimisation, label)
    "ours": ("online", True, True, "adaptive", "3dgs", False, "Our Egocentric-GS"),
    "no_viba": ("factory", True, True, "adaptive", "3dgs", False, "w/o VIBA"),
    "no_motion_sampling": ("online", True, True, "centre", "3dgs", False, "w/o motion sampling"),
    "no_scene_gamma": ("online", True, False, "adaptive", "3dgs", False, "w/o scene gamma"),
    "splatfacto": ("factory", False, True, "centre", "3dgs", False, "splatfacto"),
    "on_the_move": ("factory", False, True, "velocity_shift", "3dgs", True, "3DGS-on-move"),
    "ours_2dgs": ("online", True, True, "adaptive", "2dgs", False, "Ours 2D-GS"),
    "2dgs_no_motion_sampling": ("online", True, True, "centre", "2dgs", False, "2DGS w/o motion sampling"),
}


def test_registry_is_complete():
    assert set(METHODS) == set(EXPECTED)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_switches(name):
    m = get_method(name)
    cal, formation, scene_gamma, ms, mode, pose_opt, label = EXPECTED[name]
    assert (m.calibration, m.formation, m.scene_gamma, m.motion_sampling, m.splat_mode, m.pose_optimisation) == (
        cal, formation, scene_gamma, ms, mode, pose_opt)
    assert m.label == label
    assert m.response_gamma == 2.2
    assert m.name == name


def test_ablations_differ_from_ours_in_exactly_one_switch():
    ours = get_method("ours").to_dict()
    keys = ("calibration", "formation", "scene_gamma", "motion_sampling", "splat_mode", "pose_optimisation")
    for name, switch in [("no_viba", "calibration"), ("no_motion_sampling", "motion_sampling"),
                         ("no_scene_gamma", "scene_gamma"), ("ours_2dgs", "splat_mode")]:
        d = get_method(name).to_dict()
        assert [k for k in keys if d[k] != ours[k]] == [switch], name


def test_table_labels():
    assert get_method("ours").label_for("dtc") == "Ours (3D-GS)"
    assert get_method("ours").label_for("aria") == "Our Egocentric-GS"
    assert get_method("2dgs_no_motion_sampling").label_for("dtc") == "w/o motion sampling"
    assert "quest3" in get_method("no_viba").tables and "quest3" not in get_method("splatfacto").tables


def test_models_rolling_shutter():
    assert get_method("ours").models_rolling_shutter and get_method("on_the_move").models_rolling_shutter
    assert not get_method("splatfacto").models_rolling_shutter


def test_bad_names_and_switches():
    with pytest.raises(ValueError, match="unknown method 'nope'.*ours"):
        get_method("nope")
    with pytest.raises(ValueError, match="motion_sampling"):
        MethodSpec(name="x", label="x", calibration="online", formation=True, response_gamma=2.2, scene_gamma=True,
                   motion_sampling="wobble", splat_mode="3dgs", pose_optimisation=False)
    with pytest.raises(ValueError, match="calibration"):
        MethodSpec(name="x", label="x", calibration="viba", formation=True, response_gamma=2.2, scene_gamma=True,
                   motion_sampling="centre", splat_mode="3dgs", pose_optimisation=False)


def test_render_exposure_samples():
    from egobench.model.methods import get_method

    assert get_method("on_the_move").render_exposure_samples == 2  # velocity shift renders blur
    for name in ("ours", "no_motion_sampling", "splatfacto", "ours_2dgs"):
        assert get_method(name).render_exposure_samples == 1
