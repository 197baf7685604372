"""Why the vector env solves rebalancing once per episode: tied optima and the joint solve, measured.

Collects the rebalancing instances (idle, target) a vector env meets with uniform random actions,
then reports on the city's full min-cost-flow network (the coordinator's):

* ``tied``: the share of instances whose optimum is not unique, by an exact test: an optimal
  transportation plan x is the only one iff its residual graph has no cycle of zero reduced cost
  (potentials from Bellman-Ford on the residual graph; see :func:`tied`). With whole-step travel
  costs almost every instance is tied, so a solver other than the coordinator's (or the same
  solver on another network, e.g. one holding several episodes) returns other flows;
* ``per-episode us``: the coordinator's exact solve, one OR-Tools network per episode (what the
  vector env does);
* ``joint us``: one OR-Tools network holding B episodes as disjoint components, per episode, and
  ``joint equal``: the share of instances where it returns the per-episode flows.

    python benchmarks/rebalance_ties.py [--scenario nyc_brooklyn] [--num-envs 256] [--steps 40]
"""

from __future__ import annotations

import argparse
import os
import time

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

import marl_amod  # noqa: E402


def _closure(reach: np.ndarray) -> np.ndarray:
    """Reflexive-transitive closure of (K, M, M) boolean relations by repeated squaring."""
    m = reach.shape[-1]
    out = reach | np.eye(m, dtype=bool)
    for _ in range(int(np.ceil(np.log2(max(m, 2))))):
        out = (out.astype(np.int32) @ out.astype(np.int32)) > 0
    return out


def tied(plan: np.ndarray, cost: np.ndarray) -> np.ndarray:
    """(K,) True where the optimal transportation plan (K, S, D) with costs (S, D) is not unique.

    Another optimum differs from ``plan`` by zero-cost cycles of its residual graph (raise x_ij
    along an arc, lower x_kj with x_kj > 0, ...). With optimal potentials every residual arc has
    reduced cost >= 0, so such a cycle uses zero-reduced-cost arcs only. It exists iff either the
    support of ``plan`` holds a cycle (not a forest), or some unused zero-reduced-cost arc i -> j
    closes a path j -> ... -> i of used arcs back and zero-reduced-cost arcs forth.
    """
    k, s, d = plan.shape
    used = plan > 0
    u, v = np.zeros((k, s), np.int64), np.zeros((k, d), np.int64)  # Bellman-Ford from a virtual root
    for _ in range(4 * (s + d)):
        v_new = np.minimum(v, (u[:, :, None] + cost).min(axis=1))
        u_new = np.minimum(u, np.where(used, v_new[:, None, :] - cost, np.iinfo(np.int64).max // 4).min(axis=2))
        if (v_new == v).all() and (u_new == u).all():
            break
        u, v = u_new, v_new
    reduced = cost + u[:, :, None] - v[:, None, :]
    if (reduced < 0).any() or reduced[used].any():
        raise ValueError("the plan is not optimal")
    zero = reduced == 0
    as_int = used.astype(np.int32)
    senders_reach = _closure((zero.astype(np.int32) @ as_int.transpose(0, 2, 1)) > 0)  # a -> b via some j
    back = (as_int.transpose(0, 2, 1) @ senders_reach.astype(np.int32)) > 0  # (K, D, S): j reaches i
    closes = (zero & ~used & back.transpose(0, 2, 1)).any(axis=(1, 2))
    linked = _closure((as_int @ as_int.transpose(0, 2, 1)) > 0)  # senders sharing a destination
    active_s, active_d = used.any(axis=2), used.any(axis=1)
    components = (active_s & ~np.tril(linked, -1).any(axis=2)).sum(axis=1)
    not_forest = used.sum(axis=(1, 2)) != active_s.sum(axis=1) + active_d.sum(axis=1) - components
    return closes | not_forest


def plans(idle: np.ndarray, target: np.ndarray, flows: np.ndarray) -> np.ndarray:
    """(K, N, N + 1) transportation plans of the full network from the coordinator's flows:
    moves off the diagonal, own vehicles kept for the own target, the rest to the sink."""
    need = np.maximum(target, 0)
    k, n = idle.shape
    plan = np.zeros((k, n, n + 1), dtype=np.int64)
    plan[:, :, :n] = flows
    plan[:, np.arange(n), np.arange(n)] = need - flows.sum(axis=1)
    plan[:, :, n] = idle - plan[:, :, :n].sum(axis=2)
    return plan


def joint(idle: np.ndarray, need: np.ndarray, cost: np.ndarray) -> np.ndarray:
    """(B, N, N) flows of one OR-Tools network holding B full networks as disjoint components."""
    from ortools.graph.python import min_cost_flow

    b, n = idle.shape
    m = 2 * n + 1
    rows = np.arange(n)
    tail = np.concatenate([np.repeat(rows, n), rows])
    head = np.concatenate([np.tile(rows + n, n), np.full(n, 2 * n)])
    offset = (np.arange(b) * m)[:, None]
    smcf = min_cost_flow.SimpleMinCostFlow()
    arcs = smcf.add_arcs_with_capacity_and_unit_cost(
        (tail + offset).ravel(), (head + offset).ravel(), idle[:, tail].ravel(),
        np.tile(np.concatenate([cost.ravel(), np.zeros(n, np.int64)]), b),
    )
    smcf.set_nodes_supplies(np.arange(b * m), np.concatenate([idle, -need, (need.sum(1) - idle.sum(1))[:, None]], axis=1).ravel())
    if smcf.solve() != smcf.OPTIMAL:
        raise RuntimeError("joint solve failed")
    flows = smcf.flows(arcs).reshape(b, n * n + n)[:, : n * n].reshape(b, n, n)
    flows[:, rows, rows] = 0
    return flows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="nyc_brooklyn")
    parser.add_argument("--num-envs", type=int, default=256)
    parser.add_argument("--steps", type=int, default=40)
    args = parser.parse_args()
    from marl_amod.coordinator.rebalance import Rebalancer
    from marl_amod.scenario import load_city

    city = load_city(args.scenario)
    venv = marl_amod.vector_env(city, num_envs=args.num_envs)
    rng = np.random.default_rng(0)
    venv.reset(seed=0)
    idles, targets = [], []
    for _ in range(args.steps):
        actions = rng.random((args.num_envs, venv.num_agents))
        idles.append(venv.system.sim.idle.copy())
        targets.append(venv.system.targets_from_weights(actions))
        *_, trunc, _ = venv.step(actions)
        if trunc.all():
            venv.reset()
    idle, target = np.concatenate(idles), np.concatenate(targets)
    need = np.maximum(target, 0)
    short = (need > idle).any(axis=1)
    idle, target, need = idle[short], target[short], need[short]
    solver = Rebalancer(city.reb_time)  # the full network, as on any city without the triangle inequality
    start = time.perf_counter()
    flows = solver.many(idle, target)
    per_episode = (time.perf_counter() - start) / len(idle) * 1e6
    cost = np.concatenate([solver.cost, np.zeros((city.n_regions, 1), np.int64)], axis=1)
    tie = tied(plans(idle, target, flows), cost)
    b = args.num_envs
    start = time.perf_counter()
    together = np.concatenate([joint(idle[k : k + b], need[k : k + b], solver.cost) for k in range(0, len(idle), b)])
    joint_us = (time.perf_counter() - start) / len(idle) * 1e6
    same = (together == flows).all(axis=(1, 2))
    print(f"| scenario | instances | tied | per-episode us | joint us (B={b}) | joint equal |")
    print("|---|---:|---:|---:|---:|---:|")
    print(f"| {args.scenario} | {len(idle):,} | {tie.mean():.1%} | {per_episode:.0f} | {joint_us:.0f} | {same.mean():.1%} |")


if __name__ == "__main__":
    main()
