"""Model-predictive control on the paper's time-expanded network-flow problem (eq. global_obj..c5).

At control step t the system has already dispatched, so the plan starts from the idle vehicles
left after dispatch. Over a receding horizon of H steps (relative k = 0..H-1, absolute t + k)
the LP chooses

* rebalancing flows y[k, i, j] >= 0 for k = 0..H-1 (y[k, i, i] = vehicles that stay idle),
* passenger flows 0 <= x[k, i, j] <= d[k, i, j] for k = 1..H-1 (step-t dispatch is fixed),

maximising sum (p - c) x - c_reb y, subject to conservation with the simulator's timing: a
vehicle leaving in step s on a trip of tau steps is idle (dispatchable) from step s + tau + 1,
staying counts as tau = 0, and vehicles already on the road join the idle pool the step after
``sim.arrivals`` says they arrive:

    k = 0:   sum_j y[0, i, j]                 = idle_i
    k >= 1:  sum_j (x[k, i, j] + y[k, i, j])  = arrivals[t + k - 1, i]
                                               + sum_{s + tau_s(j, i) + 1 = k} (x[s, j, i] + y[s, j, i])

Steps past the episode's last dispatch carry no demand. Only y[0] is applied: it is turned into
per-region targets idle_i + inflow_i - outflow_i that the coordinator's min-cost flow meets.
The constraint matrix is a network matrix (every flow leaves one node and enters at most one),
so a HiGHS vertex is integral for integral demand (the oracle); fractional plans (forecasts)
are rounded by largest remainder, which keeps the fleet size.

``mpc-scenarios`` solves a two-stage version instead of planning on one demand: S Poisson draws
around the forecast, one copy of the LP per draw, a single y[0] shared by all copies (the only
decision taken before the demand is seen), the mean profit as objective (:func:`solve_scenarios`).

Two solver paths build the same LP: ``"scipy"`` assembles the sparse matrix from index arrays
and solves it with HiGHS's dual simplex as ``linprog(method="highs-ds")`` would, vertex for vertex,
without linprog's wrapping (:mod:`marl_amod.baselines.highs`); ``"cvxpy"`` builds a DPP-parameterised problem once per
policy (demand, margins, idle, arrivals and the time-varying trip-time arrival masks are
parameters) and re-solves it with HiGHS.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from marl_amod.baselines.base import FlowPolicy
from marl_amod.baselines.highs import solve_lp
from marl_amod.errors import ConfigError, SolverError
from marl_amod.scenario.types import City, step_rows
from marl_amod.system import FleetSystem
from marl_amod.validation import as_count, as_real, as_seed

if TYPE_CHECKING:
    import scipy.sparse as sp

MPCBackend = Literal["scipy", "cvxpy"]
DEFAULT_HORIZON = 20  # RL4AMOD's MPC default T; a whole 20-step episode on the bundled cities


@dataclass
class FlowPlan:
    """An LP solution over the horizon; arrays (H, N, N), relative step first."""

    x: np.ndarray  # passenger flows (x[0] is the fixed, already applied dispatch: zeros)
    y: np.ndarray  # rebalancing flows, diagonal = vehicles that stay
    objective: float  # planned profit over the horizon (money)


@dataclass
class PlanData:
    """Everything one MPC solve reads, in relative steps k = 0..H-1."""

    idle: np.ndarray  # (N,) idle vehicles now (after dispatch when dispatch is fixed)
    arrivals: np.ndarray  # (H, N) vehicles arriving in step t + k (idle from t + k + 1)
    demand: np.ndarray  # (H, N, N) requests; demand[0] only used when dispatch is planned too
    margin: np.ndarray  # (H, N, N) price - trip cost
    trip_time: np.ndarray  # (H, N, N) int trip durations in steps
    reb_time: np.ndarray  # (N, N) int
    reb_cost: np.ndarray  # (N, N)
    plan_dispatch_now: bool = False  # True: idle is before dispatch and x[0] is a decision


def plan_data(
    city: City, t: int, idle: np.ndarray, arrivals: np.ndarray, demand: np.ndarray, horizon: int,
    *, plan_dispatch_now: bool = False,
) -> PlanData:
    """Slice the city's tables for steps t..t+H-1; ``demand`` is (H, N, N) already aligned.

    Steps past the last control step (city.horizon - 1) or the tabulated steps get no demand.
    """
    h = horizon
    steps = t + np.arange(h)
    live = steps <= city.horizon - 1
    idx = np.minimum(steps, city.n_steps - 1)
    arr = step_rows(arrivals, steps)
    return PlanData(
        idle=np.asarray(idle, dtype=float),
        arrivals=arr.astype(float),
        demand=np.asarray(demand, dtype=float) * live[:, None, None],
        margin=city.margin[idx],
        trip_time=city.trip_time[idx].astype(np.int64),
        reb_time=city.reb_time.astype(np.int64),
        reb_cost=np.asarray(city.reb_cost, dtype=float),
        plan_dispatch_now=plan_dispatch_now,
    )


# ---------------------------------------------------------------------------------- sparse LP
def lp_matrices(data: PlanData) -> tuple[np.ndarray, sp.csr_matrix, np.ndarray, np.ndarray]:
    """(cost c, equality matrix A, rhs b, upper bounds) of the min-form LP over z = [x, y].

    Columns: x[k, i, j] at k*N*N + i*N + j, y at H*N*N + the same. Rows: (k, i) at k*N + i.
    """
    import scipy.sparse as sp

    h, n = data.demand.shape[0], data.idle.shape[0]
    nn = n * n
    k, i, j = np.meshgrid(np.arange(h), np.arange(n), np.arange(n), indexing="ij")
    k, i, j = k.ravel(), i.ravel(), j.ravel()
    col = k * nn + i * n + j
    tau_x = data.trip_time.reshape(-1)  # (H*N*N,) in the same (k, i, j) order
    tau_y = np.broadcast_to(data.reb_time, (h, n, n)).reshape(-1)
    rows, cols, vals = [], [], []
    for offset, tau in ((0, tau_x), (h * nn, tau_y)):
        rows += [k * n + i]  # leaves i in step k
        cols += [offset + col]
        vals += [np.ones(col.size)]
        arrive = k + tau + 1  # idle again at j in relative step k + tau + 1
        inside = arrive < h
        rows += [arrive[inside] * n + j[inside]]
        cols += [offset + col[inside]]
        vals += [-np.ones(inside.sum())]
    a = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(h * n, 2 * h * nn))
    b = np.empty((h, n))
    b[0] = data.idle
    b[1:] = data.arrivals[:-1]
    cost = np.concatenate([-data.margin.reshape(-1), np.broadcast_to(data.reb_cost, (h, n, n)).reshape(-1)])
    ub_x = data.demand.copy()
    if not data.plan_dispatch_now:
        ub_x[0] = 0.0
    ub = np.concatenate([ub_x.reshape(-1), np.full(h * nn, np.inf)])
    return cost, a, b.reshape(-1), ub


def solve_scipy(data: PlanData) -> FlowPlan:
    """The LP through scipy's HiGHS interface (dual simplex: a vertex, hence integral for integral data)."""
    h, n = data.demand.shape[0], data.idle.shape[0]
    cost, a, b, ub = lp_matrices(data)
    z, fun = solve_lp(cost, "MPC LP", a_eq=a, b_eq=b, ub=ub)
    z = z.reshape(2, h, n, n)
    return FlowPlan(x=z[0], y=z[1], objective=-fun)


def solve_scenarios(scenarios: list[PlanData]) -> FlowPlan:
    """The two-stage LP over S demand scenarios: one flow network per scenario, one shared y[0].

    Only the first rebalancing is applied, so only it must be decided before the demand is known
    (non-anticipativity); every later flow adapts to its scenario. The objective is the mean
    profit over the scenarios. Each scenario's block is :func:`lp_matrices` as is; the blocks are
    stacked along the diagonal and their y[0] columns mapped onto one set of N*N columns (the
    k = 0 rows then repeat once per scenario; HiGHS's presolve drops the copies).
    Returns y[0] (shared) and the scenario-mean of every other flow, with the mean objective.
    """
    import scipy.sparse as sp

    if not scenarios:
        raise ConfigError("the scenario MPC needs at least one scenario")
    s_count = len(scenarios)
    h, n = scenarios[0].demand.shape[0], scenarios[0].idle.shape[0]
    nn, width = n * n, 2 * h * n * n  # columns per scenario: [x (H*N*N), y (H*N*N)]
    y0 = np.arange(h * nn, h * nn + nn)  # the local columns of y[0]
    own = np.setdiff1d(np.arange(width), y0)  # every other local column: one copy per scenario
    local_to_global = np.empty((s_count, width), dtype=np.int64)
    local_to_global[:, y0] = np.arange(nn)  # shared: global columns 0..N*N-1
    local_to_global[:, own] = nn + np.arange(s_count)[:, None] * own.size + np.arange(own.size)
    rows, cols, vals, rhs = [], [], [], []
    cost = np.zeros(nn + s_count * own.size)
    ub = np.full(cost.size, np.inf)
    for s, data in enumerate(scenarios):  # S sparse blocks, vectorised inside
        c, a, b, u = lp_matrices(data)
        a = a.tocoo()
        rows.append(a.row + s * h * n)
        cols.append(local_to_global[s, a.col])
        vals.append(a.data)
        rhs.append(b)
        np.add.at(cost, local_to_global[s], c / s_count)  # y[0]'s cost sums to one copy's
        ub[local_to_global[s, own]] = u[own]
    a_all = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(s_count * h * n, cost.size)
    )
    z, fun = solve_lp(cost, "scenario MPC LP", a_eq=a_all, b_eq=np.concatenate(rhs), ub=ub)
    per = z[local_to_global].reshape(s_count, 2, h, n, n).mean(axis=0)  # y[0] identical in every copy
    return FlowPlan(x=per[0], y=per[1], objective=-fun)


class CvxpyMPC:
    """The same LP as a DPP-parameterised cvxpy problem, compiled once and re-solved with HiGHS.

    Only dispatch-fixed plans (the policy's case). Trip times vary with the time of day, so the
    arrival pattern of passenger flows is a parameter: mask[s, k][j, i] = 1 when a trip j->i
    starting in relative step s is idle again in step k.
    """

    def __init__(self, city: City, horizon: int) -> None:
        import cvxpy as cp

        if horizon < 2:
            raise ConfigError("the cvxpy MPC path needs a horizon of at least 2 steps")
        n, h = city.n_regions, horizon
        self.n, self.h = n, h
        self.reb_time = city.reb_time.astype(np.int64)
        self.x = [cp.Variable((n, n), nonneg=True) for _ in range(h)]  # x[0] unused (fixed dispatch)
        self.y = [cp.Variable((n, n), nonneg=True) for _ in range(h)]
        self.d = [cp.Parameter((n, n), nonneg=True) for _ in range(h)]
        self.m = [cp.Parameter((n, n)) for _ in range(h)]
        self.idle = cp.Parameter(n, nonneg=True)
        self.arr = cp.Parameter((h, n), nonneg=True)
        self.mask = {(s, k): cp.Parameter((n, n), nonneg=True) for s in range(1, h) for k in range(s + 2, h)}
        reb_cost = np.asarray(city.reb_cost, dtype=float)
        objective = sum(cp.sum(cp.multiply(self.m[k], self.x[k])) for k in range(1, h))
        objective -= sum(cp.sum(cp.multiply(reb_cost, self.y[k])) for k in range(h))
        cons = [cp.sum(self.y[0], axis=1) == self.idle]
        for k in range(1, h):
            cons.append(self.x[k] <= self.d[k])
            inflow = self.arr[k - 1]
            for s in range(k):
                y_mask = (s + self.reb_time + 1 == k).astype(float)
                if y_mask.any():
                    inflow = inflow + cp.sum(cp.multiply(y_mask, self.y[s]), axis=0)
                if (s, k) in self.mask:
                    inflow = inflow + cp.sum(cp.multiply(self.mask[s, k], self.x[s]), axis=0)
            cons.append(cp.sum(self.x[k], axis=1) + cp.sum(self.y[k], axis=1) == inflow)
        self.problem = cp.Problem(cp.Maximize(objective), cons)

    def solve(self, data: PlanData) -> FlowPlan:
        import cvxpy as cp

        if data.plan_dispatch_now or data.demand.shape[0] != self.h:
            raise ConfigError("the cvxpy MPC path solves dispatch-fixed plans of its own horizon only")
        self.idle.value = data.idle
        self.arr.value = data.arrivals
        for k in range(self.h):
            self.d[k].value = data.demand[k]
            self.m[k].value = data.margin[k]
        for (s, k), p in self.mask.items():
            p.value = (s + data.trip_time[s] + 1 == k).astype(float)
        self.problem.solve(solver=cp.HIGHS)
        if self.problem.status not in ("optimal", "optimal_inaccurate"):
            raise SolverError(f"MPC LP (cvxpy/HiGHS) failed: status {self.problem.status}")
        x = np.stack([np.zeros((self.n, self.n))] + [v.value for v in self.x[1:]])
        y = np.stack([v.value for v in self.y])
        return FlowPlan(x=x, y=y, objective=float(self.problem.value))


# ---------------------------------------------------------------------------------- policies
class MPCPolicy(FlowPolicy):
    """Receding-horizon MPC: solve the fleet LP after each dispatch and apply its first rebalancing.

    After each decision ``last_plan`` holds the whole plan it came from (every step's passenger and
    rebalancing flows, and the objective) and ``solve_seconds`` each solve's time, for inspection.
    """

    name = "mpc"

    def __init__(self, horizon: int = DEFAULT_HORIZON, backend: MPCBackend = "scipy") -> None:
        self.horizon = as_count(horizon, "MPC horizon (steps)", lower=1)
        if backend not in ("scipy", "cvxpy"):
            raise ConfigError(f"MPC backend must be 'scipy' or 'cvxpy', got {backend!r}")
        self.backend = backend
        self._cvx: CvxpyMPC | None = None
        self._cvx_city: City | None = None
        self.solve_seconds: list[float] = []
        self.last_plan: FlowPlan | None = None

    def reset(self, system: FleetSystem, rng: np.random.Generator) -> None:
        super().reset(system, rng)
        self.solve_seconds = []
        if self.backend == "cvxpy" and self._cvx_city is not system.city:
            self._cvx = CvxpyMPC(system.city, self.horizon)  # compiled once, reused every episode
            self._cvx_city = system.city

    def forecast(self, system: FleetSystem, steps: np.ndarray) -> np.ndarray:
        """(H, N, N) demand believed for absolute ``steps`` (clipped to the tabulated range)."""
        raise NotImplementedError

    def believed_demand(self, system: FleetSystem) -> np.ndarray:
        """(H, N, N) requests the plan may serve: the forecast, plus, when requests wait
        (``max_wait`` > 0), those still open after this step's dispatch that will not have left by
        the next step (the simulator's ``carried_over``), added to step t + 1.

        A waiting request could also be served later than t + 1; offering it once, at the
        first chance, keeps the LP a plain network flow and is where the dispatch takes it.
        """
        return self.add_waiting(system, self.forecast(system, system.sim.t + np.arange(self.horizon)).astype(float))

    def add_waiting(self, system: FleetSystem, demand: np.ndarray) -> np.ndarray:
        """``demand`` (..., H, N, N) plus the requests still waiting after dispatch, at relative step 1."""
        sim = system.sim
        if self.horizon > 1 and sim.t + 1 < system.city.horizon:
            demand[..., 1, :, :] += sim.carried_over()
        return demand

    def problem(self, system: FleetSystem) -> PlanData | list[PlanData]:
        """The LP's data for this step (built outside the timed solve)."""
        sim = system.sim
        return plan_data(system.city, sim.t, sim.idle, sim.arrivals, self.believed_demand(system), self.horizon)

    def solve(self, problem: PlanData | list[PlanData]) -> FlowPlan:
        """The plan of :meth:`problem`'s data."""
        return self._cvx.solve(problem) if self._cvx is not None else solve_scipy(problem)

    def plan(self, system: FleetSystem) -> FlowPlan:
        problem = self.problem(system)
        start = time.perf_counter()
        plan = self.solve(problem)
        self.solve_seconds.append(time.perf_counter() - start)
        self.last_plan = plan
        return plan

    def flows(self, system: FleetSystem) -> np.ndarray:
        return self.plan(system).y[0]


class MPCOracle(MPCPolicy):
    """MPC with perfect knowledge of the demand the episode will actually draw (an upper bound)."""

    name = "mpc-oracle"

    def forecast(self, system: FleetSystem, steps: np.ndarray) -> np.ndarray:
        demand = system.sim.demand
        idx = np.minimum(steps, demand.shape[0] - 1)
        return demand[idx] * (steps < demand.shape[0])[:, None, None]


class MPCForecast(MPCPolicy):
    """MPC fed the scenario's expected demand, optionally with unbiased multiplicative noise.

    It reads ``city.forecast_rate``: under a scenario's events (a demand shock) it plans with the
    usual demand, not knowing the event; MPC-Oracle sees the draw, event included.

    ``noise`` is the standard deviation of a mean-one log-normal factor per OD pair and step,
    drawn from the policy rng (so runs are reproducible); 0 gives the expected rates.

    ``demand_scale`` plans on that multiple of the expected demand. Demand is Poisson and a lost
    request costs far more than a rebalancing trip, so provisioning for the mean is not the best
    bet (the newsvendor's optimum is a quantile above it); a scale > 1 hedges. 1 is the plain
    forecast. Requests already waiting (``max_wait`` > 0) are known, so they are never scaled.
    """

    name = "mpc-forecast"

    def __init__(
        self, horizon: int = DEFAULT_HORIZON, backend: MPCBackend = "scipy", noise: float = 0.0, demand_scale: float = 1.0,
    ) -> None:
        super().__init__(horizon, backend)
        self.noise = as_real(noise, "forecast noise", minimum=0)
        self.demand_scale = as_real(demand_scale, "forecast demand_scale", above=0)
        if self.demand_scale != 1.0:  # results, datasets and cards say which teacher it was
            self.name = f"{MPCForecast.name}+scale{self.demand_scale:g}"

    def forecast(self, system: FleetSystem, steps: np.ndarray) -> np.ndarray:
        rate = system.city.forecast_rate
        idx = np.minimum(steps, rate.shape[0] - 1)
        d = rate[idx] * (steps < rate.shape[0])[:, None, None]
        if self.demand_scale != 1.0:
            d = d * self.demand_scale
        if self.noise > 0:
            sigma2 = np.log1p(self.noise**2)
            d = d * self.rng.lognormal(-sigma2 / 2, np.sqrt(sigma2), size=d.shape)
        return d


class MPCScenarios(MPCForecast):
    """Two-stage MPC: the first rebalancing chosen against S sampled demand scenarios at once.

    Planning on the mean (MPC-Forecast) under-provisions for Poisson demand, and a fixed scale
    only guesses how much to hedge. Here each scenario draws Poisson requests around
    ``city.forecast_rate`` for the horizon's steps (from the policy rng, so runs are
    reproducible); one LP (:func:`solve_scenarios`) shares y[0] across the scenarios and lets
    every later flow follow its own scenario, maximising the mean profit. Requests already
    waiting (``max_wait`` > 0) are known and added to every scenario. It sees nothing a policy
    does not: the forecast rates, the fleet, and its own random draws.

    ``crn_seed`` (common random numbers) draws step t's scenarios from a generator seeded by
    (``crn_seed``, t, :attr:`CRN_STREAM`) instead of the policy rng, the same in every episode and on every call. The
    plan is then a function of the state: two calls in the same state ask for the same targets,
    so a clone of it is shown one plan per state instead of the spread of 16-draw plans.
    """

    name = "mpc-scenarios"
    DEFAULT_SCENARIOS = 8
    CRN_STREAM = 5021
    """the third seed word of the common random numbers: (``crn_seed``, t) alone is episode t's
    demand stream of seed ``crn_seed`` (:func:`~marl_amod.evaluation.episode_seeds`), whose
    scenario at step 0 of episode 0 would be the episode's own future demand"""

    def __init__(
        self, horizon: int = DEFAULT_HORIZON, scenarios: int = DEFAULT_SCENARIOS, crn_seed: int | None = None,
    ) -> None:
        super().__init__(horizon, "scipy")
        self.scenarios = as_count(scenarios, "mpc-scenarios scenarios", lower=1)
        self.crn_seed = None if crn_seed is None else as_seed(crn_seed, "mpc-scenarios crn_seed (or none)")
        if self.scenarios != self.DEFAULT_SCENARIOS:  # results, datasets and cards say which teacher it was
            self.name = f"{MPCScenarios.name}+s{self.scenarios}"
        if self.crn_seed is not None:
            self.name = f"{self.name}+crn{self.crn_seed}"

    def sample_demand(self, mean: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(S, H, N, N) request counts drawn around the (H, N, N) expected demand."""
        return rng.poisson(mean, size=(self.scenarios, *mean.shape)).astype(float)

    def scenario_demand(self, system: FleetSystem) -> np.ndarray:
        """(S, H, N, N): the sampled future demand plus the requests already waiting."""
        t = system.sim.t
        mean = self.forecast(system, t + np.arange(self.horizon))
        rng = self.rng if self.crn_seed is None else np.random.default_rng([self.crn_seed, t, self.CRN_STREAM])
        return self.add_waiting(system, self.sample_demand(mean, rng))

    def problem(self, system: FleetSystem) -> list[PlanData]:
        """One LP's data per sampled scenario."""
        sim = system.sim
        return [plan_data(system.city, sim.t, sim.idle, sim.arrivals, d, self.horizon) for d in self.scenario_demand(system)]

    def solve(self, problem: PlanData | list[PlanData]) -> FlowPlan:
        return solve_scenarios(problem)
