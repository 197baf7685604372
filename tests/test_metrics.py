"""Episode metrics: the Gini coefficient and the equity-of-service metrics built on it."""

from __future__ import annotations

import numpy as np
import pytest

from marl_amod.evaluation import evaluate
from marl_amod.metrics import METRICS, episode_metrics, gini, metric_arrays, normalised_score, region_metrics, score_anchors
from marl_amod.sim.macro import EpisodeTotals


def _pairwise_gini(x: np.ndarray) -> float:
    """The textbook definition: sum_ij |x_i - x_j| / (2 n^2 mean)."""
    return float(np.abs(x[:, None] - x[None, :]).sum() / (2 * x.size**2 * x.mean()))


@pytest.mark.parametrize("n", [1, 2, 5, 100])
def test_gini_of_equal_values_is_zero_and_of_one_hot_is_n_minus_one_over_n(n):
    assert gini(np.full(n, 3.7)) == pytest.approx(0.0, abs=1e-12)
    one_hot = np.zeros(n)
    one_hot[n // 2] = 5.0
    assert gini(one_hot) == pytest.approx((n - 1) / n)


def test_gini_hand_computed_and_against_the_pairwise_definition():
    # |differences| of 1, 2, 3, 4 sum to 20 over ordered pairs; 20 / (2 * 16 * 2.5) = 0.25
    assert gini([4.0, 1.0, 3.0, 2.0]) == pytest.approx(0.25)
    x = np.random.default_rng(0).exponential(size=(3, 37))
    np.testing.assert_allclose(gini(x), [_pairwise_gini(row) for row in x])
    np.testing.assert_allclose(gini(x.T, axis=0), gini(x))


def test_gini_of_nothing_is_zero_and_negative_values_raise():
    assert gini(np.zeros(4)) == 0.0
    assert gini(np.array([])) == 0.0
    with pytest.raises(ValueError, match="non-negative"):
        gini([1.0, -1.0])


def _totals(served, demand, wait_minutes) -> EpisodeTotals:
    totals = EpisodeTotals.zeros(len(served))
    totals.served[:] = served
    totals.demand[:] = demand
    totals.wait_minutes[:] = wait_minutes
    return totals


def test_service_rate_and_fairness_leave_out_regions_where_they_are_undefined():
    # region 2 had no requests, region 3 had requests but served none
    totals = _totals(served=[4, 2, 0, 0], demand=[4, 4, 0, 2], wait_minutes=[12, 12, 0, 0])
    regions = region_metrics(totals)
    assert regions["service_rate"] == [1.0, 0.5, 0.0, 0.0]
    assert regions["wait_time"] == [3.0, 6.0, 0.0, 0.0]
    m = episode_metrics(totals, fleet=10, horizon=5)
    assert m["wait_time_gini"] == pytest.approx(gini([3.0, 6.0]))  # regions that served someone
    assert m["service_rate_gini"] == pytest.approx(gini([1.0, 0.5, 0.0]))  # regions with requests
    assert set(m) == set(METRICS)


def test_evaluation_reports_fairness_with_mean_and_std(tiny_city):
    res = evaluate("no-rebalancing", tiny_city, episodes=3, seed=0, max_wait=2)
    for key in ("wait_time_gini", "service_rate_gini"):
        per_episode = [e[key] for e in res["per_episode"]]
        assert all(0.0 <= g < 1.0 for g in per_episode)
        assert res["metrics"][key] == {"mean": pytest.approx(np.mean(per_episode)), "std": pytest.approx(np.std(per_episode))}
    rate = np.array(res["per_region"]["service_rate"])
    assert rate.shape == (tiny_city.n_regions,) and np.all((rate >= 0) & (rate <= 1))
    assert res["metrics"]["wait_time"]["mean"] > 0  # requests waited, so the wait Gini is about something


def test_batch_metrics_equal_each_episode_alone_to_the_last_bit():
    """A batch's Gini goes through one call per distinct region count; every row must still give
    exactly the numbers of its own episode (the vector env's infos equal the ParallelEnv's)."""
    rng = np.random.default_rng(3)
    b, n = 40, 9
    totals = EpisodeTotals.zeros(n, (b,))
    totals.demand[:] = rng.integers(0, 5, (b, n)) * (rng.random((b, n)) < 0.8)
    totals.served[:] = np.minimum(totals.demand, rng.integers(0, 5, (b, n)))
    totals.wait_minutes[:] = totals.served * rng.integers(0, 4, (b, n)) * 5.0
    totals.served[0], totals.demand[0] = 0, 0  # an episode where nobody asked
    totals.served[1], totals.demand[1] = 1, 1  # every region asked and was served
    batch = metric_arrays(totals, fleet=30, horizon=10)
    assert len(set((totals.served > 0).sum(axis=1))) > 3  # the groups are really mixed
    for k in range(b):
        alone = EpisodeTotals(**{f: getattr(totals, f)[k].copy() for f in EpisodeTotals.__dataclass_fields__})
        for key, value in episode_metrics(alone, fleet=30, horizon=10).items():
            assert batch[key][k] == value, (k, key)


def test_the_normalised_score_reads_equal_distribution_and_mpc_oracle_by_name():
    profits = {"mpc-oracle": 200.0, "no-rebalancing": 50.0, "equal-distribution": 100.0}
    assert score_anchors(profits) == (100.0, 200.0)  # (0, 100) whatever the order the rows came in
    assert normalised_score(250.0, *score_anchors(profits)) == 150.0
    assert score_anchors({"equal-distribution": 100.0, "mpc-forecast": 190.0}) is None  # no oracle: no score
    assert np.isnan(normalised_score(5.0, 100.0, 100.0))
