"""``cfbci bench returning``: day 1 recorded in the service's layout (replayed identically,
read back as the prior), day-2 arms summarised with paired differences and the fallbacks."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from acquisition.loaders import save_features_npz
from cfbci.bench.returning import DayJob, ReturningData, fallbacks, run_day
from cfbci.cli import main
from replay.prior import NoLabelledSignals, read_prior
from replay.rerun import replay_check


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    folder = tmp_path_factory.mktemp("returning")
    out = folder / "bench.json"
    code = main([
        "bench", "returning", "--synthetic", "errp", "--seeds", "2", "--first-seed", "100",
        "--steps", "120", "--jobs", "1", "--arms", "prior", "complemented",
        "--recordings", str(folder / "recordings"), "--json", str(out),
    ])
    assert code == 0
    return json.loads(out.read_text()), folder / "recordings"


def test_day_one_is_recorded_as_the_service_records(bench: tuple[dict, Path]) -> None:
    """The day-1 recordings replay identically (config, epochs, moves, states, events) and
    hold raw synthetic epochs, as the live source sends them; their prior is read back."""
    _, recordings = bench
    for user in (100, 101):
        path = recordings / f"day1-{user}.mcap"
        result = replay_check(path)
        assert result.divergence is None and result.moves == 120
        prior = read_prior([path])
        assert prior.space.sfreq == 256.0 and prior.space.ch_names == ("Fz", "FCz", "Cz", "Pz")
        assert 0 < len(prior.sessions[0].signals) < 120


def test_the_report(bench: tuple[dict, Path]) -> None:
    """Every arm's summary has ``cfbci simulate``'s keys, the fallbacks and (but scratch)
    the paired differences; the complemented ErrP priors are abandoned before the first
    signal, so that arm is scratch, session for session."""
    report, _ = bench
    assert list(report["arms"]) == ["scratch", "prior", "complemented"]
    scratch, complemented = report["arms"]["scratch"], report["arms"]["complemented"]
    for key in ("median_first_target_step", "mean_correct_targets", "wrong_target_rate"):
        assert key in scratch and key in report["arms"]["prior"]
    assert "paired" not in scratch and scratch["fallbacks"]["sessions"] == 0
    assert complemented["fallbacks"] == {
        "sessions": 2, "fell_back": 2, "fell_back_at": [0, 0], "trusted": 0, "trusted_at": [],
        "testing": 0, "no_prior": 0, "refused_by_power_premise": 2,
    }
    paired = complemented["paired"]["first_target_step"]
    assert paired["differences"] == [0, 0] and paired["interval_95"] == [0.0, 0.0]
    sessions = report["sessions"]
    for with_prior, without in zip(sessions["complemented"], sessions["scratch"], strict=True):
        assert with_prior.pop("decision")["premise"] < 0 and without.pop("decision") is None
        assert with_prior == without
    prior = report["arms"]["prior"]["paired"]["correct_targets"]
    assert prior["mean"] == pytest.approx(np.mean(prior["differences"]))
    assert report["config"]["users"] == [100, 101]


def test_synthetic_days_and_dataset_halves(tmp_path: Path) -> None:
    """Synthetic days: two draws of one subject (the same latency), day 2 drifted on
    request; dataset days: disjoint halves, stratified by label."""
    data = ReturningData(drift=0.2)
    one, two = data.day(7, 1), data.day(7, 2)
    assert one.epochs.shape == two.epochs.shape and not np.array_equal(one.epochs, two.epochs)
    assert "latency" in one.source and one.source.split("drift")[1] == two.source.split("drift")[1]
    assert "amplitude x0.8" in data.day(7, 2, drifted=True).source
    assert data.subject(7) != data.subject(8)
    features = np.arange(40, dtype=float).reshape(20, 2)
    labels = np.array([0] * 16 + [1] * 4)
    path = tmp_path / "d.npz"
    save_features_npz(path, features, labels)
    for split in ("stratified", "order"):
        halves = [ReturningData(path, split=split).day(3, day) for day in (1, 2)]
        rows = [set(map(tuple, half.features)) for half in halves]
        assert not rows[0] & rows[1] and len(rows[0] | rows[1]) == 20
        assert [np.bincount(h.labels).tolist() for h in halves] == [[8, 2], [8, 2]]
    order = ReturningData(path, split="order").day(3, 1)
    assert order.features[:, 0].tolist() == [0, 2, 4, 6, 8, 10, 12, 14, 32, 34]


def test_a_day_one_without_two_targets_gives_no_prior(tmp_path: Path) -> None:
    """A day 1 too short to declare two targets labels nothing: day 2's arm with its prior
    runs from scratch, session for session, and says so."""
    data, day1 = ReturningData(), str(tmp_path / "day1.mcap")
    first, _ = run_day(DayJob(data, 100, "day1", 12, (day1,)))
    assert first.correct_targets + first.wrong_targets < 2
    with pytest.raises(NoLabelledSignals, match="no labelled signal"):
        read_prior([day1])
    result, decision = run_day(DayJob(data, 100, "prior", 12, (day1,)))
    assert decision == {"outcome": "no prior", "step": None, "premise": None}
    assert (result, None) == run_day(DayJob(data, 100, "scratch", 12))
    assert fallbacks([decision])["no_prior"] == 1


def test_another_subjects_prior_declares_no_target_todays_signals_barely_raised(
    tmp_path: Path,
) -> None:
    """Synthetic user 107 (balanced accuracy 0.78) with user 108's day 1 as prior: the
    informed learner is sure of a task after 17 signals, which the blank learner gives
    0.036 (below the uniform 1/25) and its best task 0.054; corroborated by the ratio alone
    (at least half the best's), that first target was wrong, and both learners, having
    adopted its labels, locked into wrong targets (36 in 500 steps, none correct). The
    check's lift (the blank learner's posterior at least 1.5 / n_tasks) withholds it: the
    session's first target is correct."""
    data = ReturningData(accuracy=0.78)
    day1 = str(tmp_path / "day1-108.mcap")
    run_day(DayJob(data, 108, "day1", 500, (day1,)))
    result, decision = run_day(DayJob(data, 107, "other_subject", 70, (day1,)))
    assert result.first_target_step is not None
    assert result.first_correct_target_step == result.first_target_step
    assert result.wrong_targets == 0 and decision is not None
