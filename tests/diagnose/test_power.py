"""egobench.diagnose.power: the smallest testable effect is measured against the test a name must pass, the
placebos' included (a table that calls an effect testable where the run's own calibrated test could not name it
promises power the diagnosis does not have)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.stats as sps

from egobench.diagnose.power import (MDE_POWER, DetectionScale, geometric_standard_errors, placebo_critical_t,
                                     smallest_testable)
from egobench.residual.calibration import PLACEBO_MAX, beat_placebos
from egobench.residual.estimation import CauseResult

ALPHA, M, DF = 0.01, 6, 30
RANK = {"placebo_t_mean": -0.5, "placebo_t_sd": 2.0, "placebo_n": 999}


def _ctx() -> SimpleNamespace:
    return SimpleNamespace(readout_s=0.008)  # what the readout's smallest testable size reads of the context


def test_a_few_placebos_critical_t_is_where_beat_placebos_reaches_the_level():
    ts = [0.3, -1.9, 2.6, 1.1, -0.4, 3.2, -2.2, 0.9, 1.7, -1.3, 0.2, 2.9, -0.8, 1.5, -2.6, 0.6]
    level = ALPHA / M
    c = placebo_critical_t({"placebo_t": ts}, level)
    assert beat_placebos(c * (1 + 1e-9), ts)[0] == pytest.approx(level, rel=1e-6)  # the tail p at the edge
    assert beat_placebos(c * 0.99, ts)[0] > level
    assert placebo_critical_t({"placebo_centre_t": [0.1, 5.0, 0.2]}, 0.5) == pytest.approx(5.0)  # above every one
    assert placebo_critical_t({"placebo_t": ts + [math.nan]}, level) == pytest.approx(c)  # a NaN is not a draw


def test_a_rank_placebo_reaches_only_its_own_p_values_and_reads_its_sign_when_one_sided():
    level = ALPHA / M  # 0.00167: the largest rank p below it is 1 / 1000
    reach = 1 / (1 + PLACEBO_MAX)
    spread = 2.0 * math.sqrt(1 + 1 / 999)
    assert placebo_critical_t(RANK, level) == pytest.approx(0.5 + spread * sps.t.isf(reach / 2, 998))
    assert placebo_critical_t(RANK, level, one_sided=True) == pytest.approx(-0.5 + spread * sps.t.isf(reach, 998))
    assert placebo_critical_t(RANK, 0.01 / 10) == math.inf  # p = 1/1000 is not below 1/1000: never named
    assert placebo_critical_t({**RANK, "placebo_t": [9.0, 9.5, 10.0]}, level) > 10.0  # both forms: the larger
    assert placebo_critical_t({"placebo": "none"}, level) == 0.0


def test_only_placebos_of_the_frame_tests_own_statistic_are_read():
    r = CauseResult("exposure_blur", "geometric", True, statistic=11.8,
                    params={"calibration": {**RANK, "first_order_t": 13.9}, "calibration_x": {"first_order_t": 11.8}},
                    internal={"frame_se": 0.001, "frame_df": DF})
    scale = geometric_standard_errors([r])["exposure_blur"]
    assert scale.placebos == ({"first_order_t": 11.8},) and scale.one_sided  # exposure blur's test is one-sided


def test_the_smallest_testable_readout_grows_with_its_placebos_spread_and_not_without_them():
    se = 0.0004  # s of the readout error
    plain = smallest_testable({"readout": DetectionScale(se, DF)}, _ctx(), ALPHA, M)["readout"]["readout_relative_error"]
    student = sps.t.ppf(1 - ALPHA / (2 * M), DF) + sps.t.ppf(MDE_POWER, DF)
    assert plain == pytest.approx(student * se / 0.008, rel=1e-9)
    narrow = {"placebo_t": list(np.linspace(-1.0, 1.0, 16))}
    assert smallest_testable({"readout": DetectionScale(se, DF, (narrow,))}, _ctx(), ALPHA, M)["readout"][
        "readout_relative_error"] == pytest.approx(plain, rel=1e-9)  # placebos narrower than the t test: it decides
    wide = {"placebo_t": list(np.linspace(-5.0, 5.0, 16))}
    got = smallest_testable({"readout": DetectionScale(se, DF, (narrow, wide))}, _ctx(), ALPHA, M)
    expected = (placebo_critical_t(wide, ALPHA / M) + sps.t.ppf(MDE_POWER, DF)) * se / 0.008
    assert got["readout"]["readout_relative_error"] == pytest.approx(expected, rel=1e-9) and expected > 1.5 * plain
    assert smallest_testable({"readout": DetectionScale(se, DF, (RANK,))}, _ctx(), 0.01, 10) == {}  # unreachable
