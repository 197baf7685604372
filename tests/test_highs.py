"""The direct HiGHS path returns linprog's vertex, bit for bit, on the LPs MPC and INF / DTV really solve.

These LPs are degenerate (many optimal vertices), so agreement in objective is not enough: MPC
would act differently at another vertex and every MPC row of every table would move.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from marl_amod.baselines import behaviour, highs
from marl_amod.baselines.highs import solve_lp
from marl_amod.baselines.mpc import MPCForecast, lp_matrices
from marl_amod.errors import SolverError
from marl_amod.evaluation import episode_seeds
from marl_amod.policies import make_policy
from marl_amod.scenario import load_city
from marl_amod.system import FleetSystem
from tests.conftest import needs_data

bundled = pytest.mark.skipif(not highs.HAS_BUNDLED_HIGHS, reason="this scipy bundles no HiGHS core: MPC uses linprog")


def _mpc_forecast_lps(city_name: str, steps: int, seed: int = 5) -> list[tuple]:
    """The LPs of the first ``steps`` control steps of one MPC-Forecast episode: (cost, keywords)."""
    city = load_city(city_name)
    system = FleetSystem(city)
    demand_seed, rng = episode_seeds(seed, 0)
    system.reset(demand_seed)
    policy = MPCForecast()
    policy.reset(system, rng)
    lps = []
    for _ in range(steps):
        cost, a, b, ub = lp_matrices(policy.problem(system))
        lps.append((cost, {"a_eq": a, "b_eq": b, "ub": ub}))
        system.step(policy.target(system))
    return lps


def _behaviour_lps(name: str, city_name: str, steps: int, monkeypatch, seed: int = 5) -> list[tuple]:
    """The LPs the behaviour policy ``name`` (inf, dtv) solves in its first ``steps`` steps."""
    lps = []

    def record(cost, what, **rows):
        lps.append((cost, rows))
        return solve_lp(cost, what, **rows)

    monkeypatch.setattr(behaviour, "solve_lp", record)
    city = load_city(city_name)
    system = FleetSystem(city)
    demand_seed, rng = episode_seeds(seed, 0)
    system.reset(demand_seed)
    policy = make_policy(name, city)
    policy.reset(system, rng)
    for _ in range(steps):
        system.step(policy.target(system))
    assert lps, f"{name} solved no LP"
    return lps


def _assert_same_vertices(lps: list[tuple]) -> None:
    for k, (cost, rows) in enumerate(lps):
        z_direct, fun_direct = solve_lp(cost, "test LP", **rows)
        z_linprog, fun_linprog = solve_lp(cost, "test LP", **rows, direct=False)
        assert np.array_equal(z_direct, z_linprog), f"LP {k}: another vertex"
        assert fun_direct == fun_linprog


@bundled
def test_direct_highs_finds_linprogs_vertex_on_the_synthetic_city():
    _assert_same_vertices(_mpc_forecast_lps("synthetic", steps=8))


@bundled
@needs_data
@pytest.mark.parametrize("city", ["chicago", "porto"])
def test_direct_highs_finds_linprogs_vertex_on_real_cities(city):
    """Chicago and Porto are where a trimmed model (zero-bound columns dropped) changed vertices."""
    _assert_same_vertices(_mpc_forecast_lps(city, steps=10))


@bundled
@pytest.mark.parametrize("policy", ["inf", "dtv"])
@pytest.mark.parametrize("city", ["synthetic", pytest.param("nyc_brooklyn", marks=needs_data)])
def test_direct_highs_finds_linprogs_vertex_on_the_behaviour_policies_lps(policy, city, monkeypatch):
    """INF (inequalities only, some columns bounded at 0) and DTV (inequalities and an equality)."""
    _assert_same_vertices(_behaviour_lps(policy, city, steps=6, monkeypatch=monkeypatch))


@bundled
@pytest.mark.parametrize(("key", "value"), [("presolve", "off"), ("simplex_strategy", 4)])
def test_the_vertex_depends_on_the_options_so_agreement_is_not_free(monkeypatch, key, value):
    """With presolve off, or the primal simplex, HiGHS ends at other vertices of these LPs."""
    lps = _mpc_forecast_lps("synthetic", steps=4)
    reference = [solve_lp(cost, "test LP", **rows, direct=False)[0] for cost, rows in lps]
    monkeypatch.setitem(highs.LINPROG_HIGHS_DS_OPTIONS, key, value)
    moved = [not np.array_equal(solve_lp(cost, "test LP", **rows)[0], z) for (cost, rows), z in zip(lps, reference, strict=True)]
    assert any(moved)


@pytest.mark.parametrize("direct", [True, False])
def test_an_infeasible_lp_raises_a_solver_error_naming_it(direct):
    a = sp.csr_matrix(np.array([[1.0, 1.0]]))
    with pytest.raises(SolverError, match="my LP"):
        solve_lp(np.ones(2), "my LP", a_eq=a, b_eq=np.array([5.0]), ub=np.array([1.0, 1.0]), direct=direct)


@bundled
def test_a_core_that_changed_its_calls_falls_back_to_linprog_with_a_warning(monkeypatch):
    """The core is private: if a scipy release changes it, MPC warns once and keeps linprog's vertex."""
    cost, rows = _mpc_forecast_lps("synthetic", steps=1)[0]
    reference, _ = solve_lp(cost, "test LP", **rows, direct=False)

    def changed(*args, **kwargs):
        raise TypeError("passModel(): incompatible function arguments")

    monkeypatch.setattr(highs, "_solve_bundled", changed)
    monkeypatch.setattr(highs, "HAS_BUNDLED_HIGHS", True)
    with pytest.warns(UserWarning, match="linprog"):
        z, _ = solve_lp(cost, "test LP", **rows)
    assert np.array_equal(z, reference) and not highs.HAS_BUNDLED_HIGHS
