"""egobench.diagnose.power: the smallest testable effect is measured against the test a name must pass, the
placebos' included (a table that calls an effect testable where the run's own calibrated test could not name it
promises power the diagnosis does not have)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.stats as sps

from egobench.diagnose.power import MDE_POWER, DetectionScale, placebo_critical_t, smallest_testable
from egobench.residual.calibration import PLACEBO_MAX, beat_placebos

ALPHA, M, DF = 0.01, 6, 30


def _ctx() -> SimpleNamespace:
    return SimpleNamespace(readout_s=0.008)  # what the readout's smallest testable size reads of the context


def test_a_few_placebos_critical_t_is_where_beat_placebos_reaches_the_level():
    ts = [0.3, -1.9, 2.6, 1.1, -0.4, 3.2, -2.2, 0.9, 1.7, -1.3, 0.2, 2.9, -0.8, 1.5, -2.6, 0.6]
    level = ALPHA / M
    c = placebo_critical_t({"placebo_t": ts}, level)
    assert beat_placebos(c * (1 + 1e-9), ts)[0] == pytest.approx(level, rel=1e-6)  # the tail p at the edge
    assert beat_placebos(c * 0.99, ts)[0] > level
    assert placebo_critical_t({"placebo_centre_t": [0.1, 5.0, 0.2]}, 0.5) == pytest.approx(5.0)  # above every one


def test_a_rank_placebo_critical_t_is_its_normal_quantile_and_needs_a_reachable_level():
    level = ALPHA / M
    rec = {"placebo_t_mean": -0.5, "placebo_t_sd": 2.0, "placebo_n": 999}
    assert placebo_critical_t(rec, level) == pytest.approx(0.5 + 2.0 * sps.norm.isf(level / 2))
    assert placebo_critical_t(rec, 0.5 / (1 + PLACEBO_MAX)) == math.inf
    assert placebo_critical_t({"placebo": "none"}, level) == 0.0


def test_the_smallest_testable_readout_grows_with_its_placebos_spread_and_not_without_them():
    se = 0.0004  # s of the readout error
    plain = smallest_testable({"readout": (se, DF)}, _ctx(), ALPHA, M)["readout"]["readout_relative_error"]
    student = sps.t.ppf(1 - ALPHA / (2 * M), DF) + sps.t.ppf(MDE_POWER, DF)
    assert plain == pytest.approx(student * se / 0.008, rel=1e-9)
    calibrated_like_t = DetectionScale(se, DF, ({"placebo_t_mean": 0.0, "placebo_t_sd": 1.0, "placebo_n": 999},))
    assert smallest_testable({"readout": calibrated_like_t}, _ctx(), ALPHA, M)["readout"]["readout_relative_error"] \
        == pytest.approx(plain, rel=1e-9)  # placebos as narrow as the t test's own: the frame test decides
    wide = list(np.linspace(-5.0, 5.0, 16))
    narrow = {"placebo_t_mean": 0.0, "placebo_t_sd": 1.0, "placebo_n": 999}
    scale = DetectionScale(se, DF, (narrow, {"placebo_t": wide}))
    got = smallest_testable({"readout": scale}, _ctx(), ALPHA, M)["readout"]["readout_relative_error"]
    expected = (placebo_critical_t({"placebo_t": wide}, ALPHA / M) + sps.t.ppf(MDE_POWER, DF)) * se / 0.008
    assert got == pytest.approx(expected, rel=1e-9) and got > 1.5 * plain
    unreachable = DetectionScale(se, DF, ({"placebo_t_mean": 0.0, "placebo_t_sd": 1.0, "placebo_n": 999},))
    assert "readout" not in smallest_testable({"readout": unreachable}, _ctx(), 0.5 / (1 + PLACEBO_MAX), 1)
