"""Reward design, the paper's beta sweep: Graph-RL trained with trip cost c_ij = beta * tau_ij per
beta, evaluated on Luxembourg in SUMO meso; writes the figure and a table (with equity metrics).

Per beta: A2C + GCN is trained in the *macro* twin (``lux_macro`` with ``beta`` overridden;
training in SUMO for every beta does not fit a CPU session), warm-started from the shipped
``lux_macro`` policy (trained at beta = 0.3) for a short budget, then evaluated in *meso*
(``lux`` with the same beta, so each policy is scored with the cost it was trained on). A
trained policy already under ``--runs`` is reused, so a second call only re-evaluates.

    python benchmarks/beta_sweep.py                       # train + evaluate + figure + table
    python benchmarks/beta_sweep.py --betas 0.1 0.5 --episodes 200 --eval-episodes 2
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from marl_amod.algos.a2c import Args  # noqa: E402
from marl_amod.algos.registry import run_training  # noqa: E402
from marl_amod.evaluation import evaluate  # noqa: E402
from marl_amod.scenario import load_city  # noqa: E402

BETAS = (0.1, 0.2, 0.3, 0.5, 0.8)
COLUMNS = (
    "profit",
    "revenue",
    "rebalancing_cost",
    "served_demand",
    "wait_time",
    "utilization",
    "wait_time_gini",
    "service_rate_gini",
)
WARM_START = "policies/a2c_gnn_lux_macro.pt"


def train_beta(beta: float, runs: Path, episodes: int, time_limit_s: float, init_policy: str | None) -> tuple[Path, dict]:
    """Train (or reuse) the policy for ``beta``; returns its path and its card."""
    tag = f"beta{beta:g}"
    policy = runs / f"a2c_gnn_lux_macro_{tag}.pt"
    if policy.exists():
        return policy, json.loads(policy.with_suffix(".json").read_text())
    runs.mkdir(parents=True, exist_ok=True)
    scenario = runs / f"lux_macro_{tag}.yaml"
    scenario.write_text(f"extends: lux_macro\nname: lux_macro_{tag}\nbeta: {beta}\n")
    args = Args(
        scenario=str(scenario), conv="gcn", episodes=episodes, time_limit_s=time_limit_s, eval_every=20, eval_episodes=3,
        run_dir=str(runs / tag), policy_out=str(policy), threads=1, init_policy=init_policy,
    )  # fmt: skip
    return policy, run_training("a2c", args)["card"]


def evaluate_beta(policy: Path, beta: float, scenario: str, episodes: int, seed: int) -> dict:
    """The policy's evaluation on ``scenario`` with the same beta, kept next to the policy so
    that a second call (or one per beta run side by side) only assembles the figure."""
    path = policy.with_name(f"{policy.stem}_{scenario}_{episodes}ep_seed{seed}.json")
    if path.exists():
        return json.loads(path.read_text())
    rec = evaluate(str(policy), load_city(scenario, beta=beta), episodes=episodes, seed=seed)
    path.write_text(json.dumps(rec))
    return rec


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--betas", type=float, nargs="+", default=list(BETAS))
    parser.add_argument("--episodes", type=int, default=600, help="macro training episodes per beta")
    parser.add_argument("--time-limit-s", type=float, default=120.0, help="training wall-time cap per beta")
    parser.add_argument("--cold", action="store_true", help="train from scratch instead of warm-starting")
    parser.add_argument("--eval-scenario", default="lux")
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--runs", default="runs/beta_sweep")
    parser.add_argument("--out", default="docs/meso")
    parser.add_argument("--train-only", action="store_true", help="train every beta, evaluate nothing")
    parser.add_argument("--no-figure", action="store_true", help="evaluate, but leave the figure and table alone")
    args = parser.parse_args()
    runs, out = Path(args.runs), Path(args.out)
    rows = []
    for beta in args.betas:
        policy, card = train_beta(beta, runs, args.episodes, args.time_limit_s, None if args.cold else WARM_START)
        trained = {"training_wall_s": card["training_wall_s"], "episodes_trained": card["episodes_trained"]}
        print(f"beta={beta:g}: {policy} ({trained})", flush=True)
        if args.train_only:
            continue
        rec = evaluate_beta(policy, beta, args.eval_scenario, args.eval_episodes, args.seed)
        rows.append({"beta": beta, "policy": str(policy), **trained, "metrics": rec["metrics"]})
        print({k: round(rec["metrics"][k]["mean"], 3) for k in COLUMNS}, flush=True)
    if args.train_only or args.no_figure:
        return
    out.mkdir(parents=True, exist_ok=True)
    payload = {
        "scenario": args.eval_scenario, "trained_in": "lux_macro", "episodes": args.eval_episodes, "seed": args.seed,
        "training_episodes": args.episodes, "training_time_limit_s": args.time_limit_s,
        "warm_start": None if args.cold else WARM_START, "rows": rows,
    }  # fmt: skip
    (out / "beta_sweep.json").write_text(json.dumps(payload, indent=1))
    write_table(payload, out / "beta_sweep.md")
    plot(rows, out / "beta_sweep.png")


def write_table(payload: dict, path: Path) -> None:
    """Markdown table: mean (std over episodes) of every column per beta."""
    lines = ["| beta | macro episodes trained | " + " | ".join(COLUMNS) + " |", "|---:|---:|" + "---:|" * len(COLUMNS)]
    for r in payload["rows"]:
        cells = []
        for k in COLUMNS:
            m = r["metrics"][k]
            digits = 3 if "gini" in k else 2 if k in ("wait_time", "utilization") else 0
            cells.append(f"{m['mean']:,.{digits}f} ± {m.get('std', 0.0):,.{digits}f}")
        lines.append(f"| {r['beta']:g} | {r.get('episodes_trained', '–')} | " + " | ".join(cells) + " |")
    path.write_text("\n".join(lines) + "\n")


def plot(rows: list[dict], path: Path) -> None:
    """The paper's figure: top profit, revenue, rebalancing cost; bottom waiting time, utilisation."""
    import matplotlib.pyplot as plt

    beta = np.array([r["beta"] for r in rows])

    def series(key: str) -> tuple[np.ndarray, np.ndarray]:
        return (np.array([r["metrics"][key]["mean"] for r in rows]), np.array([r["metrics"][key].get("std", 0.0) for r in rows]))

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(6, 6), sharex=True)
    for key, label in (("profit", "profit"), ("revenue", "revenue"), ("rebalancing_cost", "rebalancing cost")):
        m, s = series(key)
        top.errorbar(beta, m, yerr=s, marker="o", capsize=3, label=label)
    top.set_ylabel("money per episode")
    top.legend()
    m, s = series("wait_time")
    bottom.errorbar(beta, m, yerr=s, marker="o", capsize=3, color="tab:red", label="mean waiting time")
    bottom.set_ylabel("waiting time (min)")
    bottom.set_xlabel(r"$\beta$ (trip cost $c_{ij} = \beta\,\tau_{ij}$)")
    twin = bottom.twinx()
    m, s = series("utilization")
    twin.errorbar(beta, m, yerr=s, marker="s", capsize=3, color="tab:purple", label="utilisation")
    twin.set_ylabel("fleet utilisation")
    lines = bottom.get_legend_handles_labels()[0] + twin.get_legend_handles_labels()[0]
    bottom.legend(lines, [ln.get_label() for ln in lines], loc="best")
    fig.suptitle("Graph-RL on Luxembourg (SUMO meso) vs trip-cost weight")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
