"""Heuristic behaviour policies of the paper's offline-learning section: INF, DTV and PROP.

They generate offline datasets of varied quality (INF > DTV > PROP in the paper), so their
semantics follow RL4AMOD's algorithms; each is solved as an aggregated LP over region pairs
(vehicles in the same region are interchangeable) instead of a per-vehicle MILP:

* INF, informed rebalancing (Wallar et al. 2018): region r's expected requests per step over
  the next ``window`` steps, open_r, set its value; a vehicle sent from i to r earns
  open_r * (max_reb - time_ir) (staying costs no time, regions farther than ``max_reb`` steps
  are out of reach) and region r accepts at most open_r * roh * max_reb^2 of that
  time-weighted supply.
* DTV, dynamic trip-vehicle assignment (Alonso-Mora et al. 2017): the requests of the current
  step (served or not) are matched to idle vehicles with the least total travel time;
  min(vehicles, requests) matches.
* PROP: the desired distribution is proportional to the expected requests out of each region
  over the next ``lookahead`` steps (a forecast, never the realised demand).
"""

from __future__ import annotations

import numpy as np

from marl_amod.baselines.base import Policy, WeightPolicy
from marl_amod.baselines.highs import solve_lp
from marl_amod.system import FleetSystem
from marl_amod.validation import as_count, as_real


def _targets_from_moves(idle: np.ndarray, moves: np.ndarray) -> np.ndarray:
    """Targets idle + inflow - outflow from integral region-to-region moves (diagonal = stay)."""
    moves = np.floor(moves + 1e-6).astype(np.int64)
    np.fill_diagonal(moves, 0)
    target = idle - moves.sum(axis=1) + moves.sum(axis=0)
    return np.maximum(target, 0).astype(np.int64)


def _expected_outflow(system: FleetSystem, first: int, count: int) -> np.ndarray:
    """(N,) mean expected requests per step out of each region over steps first..first+count-1."""
    rate = system.city.forecast_rate  # the usual demand: a heuristic does not know a scenario's events
    steps = np.arange(first, first + count)
    steps = steps[steps < rate.shape[0]]
    if steps.size == 0:
        return np.zeros(system.city.n_regions)
    return rate[steps].sum(axis=2).sum(axis=0) / count


class Informed(Policy):
    """INF: send vehicles toward regions with many expected requests, nearer ones first."""

    name = "inf"

    def __init__(self, max_reb: int = 6, roh: float = 4.0, window: int = 10) -> None:
        self.max_reb = as_count(max_reb, "INF max_reb (steps)", lower=1)
        self.roh = as_real(roh, "INF roh", above=0)
        self.window = as_count(window, "INF window (steps)", lower=1)

    def target(self, system: FleetSystem) -> np.ndarray:
        idle = system.sim.idle
        n = idle.shape[0]
        open_req = np.rint(_expected_outflow(system, system.t + 1, self.window))
        gain = (self.max_reb - system.city.reb_time).astype(float)  # (N, N) time-discounted value
        reach = gain >= 0
        # z[i, r]: vehicles from i assigned to r; maximise sum z * open_r * gain_ir
        c = -(open_req[None, :] * gain * reach).ravel()
        rows_i = np.repeat(np.arange(n), n)  # variable (i, r) at i*n + r
        cols = np.arange(n * n)
        r_idx = np.tile(np.arange(n), n)
        a_supply = np.zeros((n, n * n))
        a_supply[rows_i, cols] = 1.0
        a_cap = np.zeros((n, n * n))
        a_cap[r_idx, cols] = np.maximum(gain, 0).ravel()
        a_ub = np.vstack([a_supply, a_cap])
        b_ub = np.concatenate([idle, open_req * self.roh * self.max_reb**2])
        ub = np.where(reach, np.inf, 0.0).ravel()
        z = solve_lp(c, "INF's LP", a_ub=a_ub, b_ub=b_ub, ub=ub)[0].reshape(n, n)
        return _targets_from_moves(idle, z)


class DynamicTripVehicle(Policy):
    """DTV: move idle vehicles to this step's request origins with the least total travel time."""

    name = "dtv"

    def target(self, system: FleetSystem) -> np.ndarray:
        sim = system.sim
        idle = sim.idle
        n = idle.shape[0]
        requests = (sim.requests() + sim.last_dispatch).sum(axis=1).astype(float)  # this step's, by origin
        matches = float(min(idle.sum(), requests.sum()))
        if matches <= 0:
            return np.full(n, -1, dtype=np.int64)
        cols = np.arange(n * n)
        a_supply = np.zeros((n, n * n))
        a_supply[np.repeat(np.arange(n), n), cols] = 1.0
        a_demand = np.zeros((n, n * n))
        a_demand[np.tile(np.arange(n), n), cols] = 1.0
        # ties broken toward staying: a tiny cost on every move keeps vehicles home when equal
        c = system.city.reb_time.astype(float).ravel() + 1e-3 * (1 - np.eye(n)).ravel()
        w = solve_lp(
            c, "DTV's LP", a_ub=np.vstack([a_supply, a_demand]), b_ub=np.concatenate([idle, requests]),
            a_eq=np.ones((1, n * n)), b_eq=np.array([matches]),
        )[0].reshape(n, n)
        return _targets_from_moves(idle, w)


class Proportional(WeightPolicy):
    """PROP: desired distribution proportional to forecast requests per origin."""

    name = "prop"

    def __init__(self, lookahead: int = 1) -> None:
        self.lookahead = as_count(lookahead, "PROP lookahead (steps)", lower=1)

    def weights(self, system: FleetSystem) -> np.ndarray:
        return _expected_outflow(system, system.t + 1, self.lookahead)

