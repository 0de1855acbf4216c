"""Unit tests of egobench.diagnose.placebo: which placebo records a trained run gets and in what order
(`trained_run_records`), the between-frame standard errors it returns, and `mark_untestable_on_trained_run`.

The order and the standard-error rule are tested with each cause's hooks replaced by recording stubs (so they do not
depend on what a placebo computes); one test runs the real placebos on a small analytic case."""

from __future__ import annotations

import numpy as np
import pytest

from egobench.diagnose.estimators import CAUSES
from egobench.diagnose.placebo import mark_untestable_on_trained_run, trained_run_records
from egobench.diagnose.power import DetectionScale
from egobench.diagnose.synthetic import make_case
from egobench.effects import EFFECTS
from egobench.effects.base import TRAINED_PLACEBO_ORDER
from egobench.residual.calibration import PlaceboRecord, TrainedRunEvidence, merge_record
from egobench.residual.estimation import CauseResult, ResidualData

FRAMES = 9


@pytest.fixture(scope="module")
def data() -> ResidualData:
    case = make_case("vignette", 0.35, seed=1, size=32, n_frames=FRAMES)
    return ResidualData(case.measured, case.predicted, case.context, np.arange(FRAMES))


def kind_of(name: str):
    return EFFECTS[name].trained_placebo


def stub_placebos(monkeypatch, calls: list, per_cause: int = 2):
    """Every cause's trained_placebos returns ``per_cause`` records tagged (name, i) and logs its call."""
    for name, cause in CAUSES.items():
        def placebos(result, evidence, name=name):
            assert isinstance(evidence, TrainedRunEvidence) and result.name == name
            calls.append((name, evidence))
            return [PlaceboRecord(None, {"tag": (name, i)}) for i in range(per_cause)]
        monkeypatch.setattr(cause, "trained_placebos", placebos)


def stub_standard_errors(monkeypatch, calls: list, values: dict):
    for name, cause in CAUSES.items():
        def se(evidence, name=name):
            calls.append(name)
            return values.get(name)
        monkeypatch.setattr(cause, "trained_standard_error", se)


def test_the_placebo_kinds_cover_every_effect():
    assert set(TRAINED_PLACEBO_ORDER) == {"photometric", "radial_centres", "velocity_permutation"}
    assert {kind_of(n) for n in EFFECTS} <= set(TRAINED_PLACEBO_ORDER) | {None}
    assert len({kind_of(n) for n in EFFECTS} - {None}) >= 2  # the order test below orders more than one kind


def test_records_follow_the_placebo_order_then_the_results_order(monkeypatch, data):
    calls: list = []
    stub_placebos(monkeypatch, calls)
    stub_standard_errors(monkeypatch, [], {})
    names = list(EFFECTS)[::-1]  # reversed registry order: the records must not follow the registry
    results = [CauseResult(n, "x", True) for n in names]
    records, _ = trained_run_records(data, results, draws=10, seed=3)
    with_kind = [n for n in names if kind_of(n) is not None]
    assert len(records) == 2 * len(with_kind)
    # each record is paired with the very result it belongs to, and a cause's records keep their own order
    for result, record in records:
        assert record.params["tag"][0] == result.name and any(result is r for r in results)
    tags = [rec.params["tag"] for _, rec in records]
    assert tags[0::2] == [(n, 0) for n, _ in tags[0::2]] and tags[1::2] == [(n, 1) for n, _ in tags[0::2]]
    order = [n for n, i in tags if i == 0]
    ranks = [TRAINED_PLACEBO_ORDER.index(kind_of(n)) for n in order]
    assert ranks == sorted(ranks)  # kinds in TRAINED_PLACEBO_ORDER
    for kind in TRAINED_PLACEBO_ORDER:  # within a kind: the results' order
        assert [n for n in order if kind_of(n) == kind] == [n for n in names if kind_of(n) == kind]
    assert kind_of(order[0]) == "photometric" and kind_of(order[-1]) == "velocity_permutation"
    # causes without a placebo kind are never asked; every call shares one evidence of this round
    assert [n for n, _ in calls] == order
    evidences = {id(ev) for _, ev in calls}
    assert len(evidences) == 1
    ev = calls[0][1]
    assert (ev.data, ev.draws, ev.seed) == (data, 10, 3)


def test_untestable_results_get_no_records(monkeypatch, data):
    calls: list = []
    stub_placebos(monkeypatch, calls, per_cause=1)
    stub_standard_errors(monkeypatch, [], {})
    results = [CauseResult("vignette", "photometric", False), CauseResult("time_offset", "geometric", True),
               CauseResult("response", "photometric", True)]
    records, _ = trained_run_records(data, results, draws=10, seed=3)
    assert [r.name for r, _ in records] == ["response", "time_offset"]
    assert [n for n, _ in calls] == ["response", "time_offset"]
    assert trained_run_records(data, [], draws=10, seed=3) == ([], {})


def test_standard_errors_only_when_a_photometric_cause_is_testable(monkeypatch, data):
    stub_placebos(monkeypatch, [], per_cause=0)
    calls: list = []
    photometric = [n for n in EFFECTS if kind_of(n) == "photometric"]
    values = {n: (0.01 * (i + 1), 8) for i, n in enumerate(photometric[:2])}  # the rest return None
    stub_standard_errors(monkeypatch, calls, values)
    geometric_only = [CauseResult(n, "geometric", True) for n in EFFECTS if kind_of(n) == "velocity_permutation"]
    geometric_only.append(CauseResult(photometric[0], "photometric", False))  # not testable: does not count
    records, se = trained_run_records(data, geometric_only, draws=10, seed=3)
    assert records == [] and se == {} and calls == []  # never computed
    results = geometric_only + [CauseResult(photometric[-1], "photometric", True)]
    _, se = trained_run_records(data, results, draws=10, seed=3)
    assert se == {n: DetectionScale(*v) for n, v in values.items()}  # a key for each cause that gives one (None: none)
    assert sorted(calls) == sorted(CAUSES)  # every cause was asked once


def test_real_placebos_on_a_small_case(data):
    """The real hooks: records in the placebo order, standard errors only for photometric causes (each a positive se
    on frames - 1 or fewer d.o.f.), and every record merges."""
    results = [CAUSES[n].fit(data) for n in EFFECTS]
    testable = [r for r in results if r.testable]
    records, se = trained_run_records(data, testable, draws=20, seed=3)
    ranks = [TRAINED_PLACEBO_ORDER.index(kind_of(r.name)) for r, _ in records]
    assert ranks == sorted(ranks) and len(set(ranks)) == 3
    assert se and set(se) <= {n for n in EFFECTS if kind_of(n) == "photometric"}
    assert all(s.se > 0 and 0 < s.df <= FRAMES - 1 and s.placebos == () for s in se.values())
    for result, record in records:
        assert isinstance(record, PlaceboRecord)
        before = result.p_value
        merge_record(result, record)
        assert result.p_value >= before
    vignette = next(r for r in testable if r.name == "vignette")
    assert "calibration" in vignette.params  # its placebo's record was written in


def test_mark_untestable_on_trained_run_uses_the_effect_reason():
    untestable = [n for n in EFFECTS if EFFECTS[n].trained_run_untestable is not None]
    assert untestable  # white balance and noise at present: the test can fail
    results = [CauseResult(n, "x", True, reason="own") for n in EFFECTS]
    results.append(CauseResult("not_an_effect", "x", True, reason="own"))
    already = CauseResult(untestable[0], "x", False, reason="too few cells")
    mark_untestable_on_trained_run(results + [already])
    for r in results:
        if r.name in untestable:
            assert (r.testable, r.reason) == (False, EFFECTS[r.name].trained_run_untestable)
        else:
            assert (r.testable, r.reason) == (True, "own")
    assert (already.testable, already.reason) == (False, "too few cells")  # an untestable result keeps its reason


@pytest.mark.parametrize("samples, testable", [([1] * FRAMES, False), ([1] * 5 + [2] * 4, False),
                                               ([1] * 4 + [3] * 5, True), ([8] * FRAMES, True)])
def test_the_readout_needs_a_run_that_renders_the_rolling_shutter(data, samples, testable):
    """A run trained at one pose sample on most frames carries no rolling shutter there: its readout is not testable
    (with the reason), every other cause is untouched; a run that sampled at least half of the frames keeps it."""
    ctx = data.ctx
    try:
        ctx.model_pose_samples = np.array(samples)
        results = [CauseResult(name, "geometric", True) for name in ("readout", "time_offset", "exposure_blur")]
        mark_untestable_on_trained_run(results, data)
        readout, *others = results
        assert readout.testable is testable and all(r.testable for r in others)
        assert testable or ("no rolling shutter" in readout.reason and "pose_sample_step_px" in readout.reason)
        ctx.model_pose_samples = None  # not a trained run's context: nothing to say
        fresh = [CauseResult("readout", "geometric", True)]
        mark_untestable_on_trained_run(fresh, data)
        assert fresh[0].testable
    finally:
        ctx.model_pose_samples = None
