"""Our numbers agree with the reference implementation's on the same city and policy.

RL4AMOD ships ``nyc_brooklyn_no_control_performance.json`` next to its city data: the episode
reward, passenger profit ("served_demand" in its logs) and rebalancing cost, in thousands, of a
policy drawing a uniform random desired distribution. Our random policy on the same calibrated
scenario must land on the same numbers.
"""

from __future__ import annotations

import pytest
from conftest import needs_data

from marl_amod.data import data_dir, read_json
from marl_amod.evaluation import evaluate


@needs_data
def test_random_policy_on_brooklyn_matches_the_reference_performance_file():
    ref = read_json(data_dir() / "macro" / "nyc_brooklyn_no_control_performance.json")
    m = evaluate("random", "nyc_brooklyn", episodes=20, seed=0)["metrics"]
    profit = m["profit"]["mean"] / 1e3
    rebalancing = m["rebalancing_cost"]["mean"] / 1e3
    assert profit == pytest.approx(ref["reward"], rel=0.04)
    assert rebalancing == pytest.approx(ref["rebalancing_cost"], rel=0.04)
    assert profit + rebalancing == pytest.approx(ref["served_demand"], rel=0.04)
