"""Reward design, the paper's beta sweep: Graph-RL trained with trip cost c_ij = beta * tau_ij per
beta, evaluated on Luxembourg in SUMO meso; writes the figure and a table (with equity metrics).

Per beta: A2C + GCN is trained from scratch in the *macro* twin (``lux_macro`` with ``beta``
overridden) with the batched recipe of ``configs/a2c/lux_macro_batched.yaml`` (16 episodes in
lockstep: thousands of episodes in a minute or two), then evaluated in *meso* (``lux`` with the
same beta, so each policy is scored with the cost it was trained for) on the report seeds.
A finished training or evaluation under ``--runs`` is reused, and an interrupted training
resumes from its state, so a second call only redraws what is missing.

    python benchmarks/beta_sweep.py                       # train + evaluate + figure + table
    python benchmarks/beta_sweep.py --betas 0.1 0.5 --episodes 2000 --eval-episodes 2
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from marl_amod.algos.common import state_path  # noqa: E402
from marl_amod.algos.registry import args_for, load_train_config, run_training  # noqa: E402
from marl_amod.evaluation import evaluate  # noqa: E402
from marl_amod.scenario import load_city  # noqa: E402

BETAS = (0.1, 0.2, 0.3, 0.5, 0.8, 1.2)
RECIPE = "configs/a2c/lux_macro_batched.yaml"
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


def train_beta(beta: float, runs: Path, recipe: str, episodes: int | None) -> tuple[Path, dict]:
    """Train (or reuse, or resume) the policy for ``beta`` with the recipe's args; returns its path and card."""
    tag = f"beta{beta:g}"
    policy = runs / f"a2c_gnn_lux_macro_{tag}.pt"
    if policy.exists():
        return policy, json.loads(policy.with_suffix(".json").read_text())
    runs.mkdir(parents=True, exist_ok=True)
    scenario = runs / f"lux_macro_{tag}.yaml"
    scenario.write_text(f"extends: lux_macro\nname: lux_macro_{tag}\nbeta: {beta}\n")
    algo, base = load_train_config(recipe)
    values = {**base.model_dump(exclude_unset=True), "scenario": str(scenario), "run_dir": str(runs / tag), "policy_out": str(policy), "init_actor": ""}
    if episodes is not None:
        values["episodes"] = episodes
    args = args_for(algo, values, recipe)
    state = state_path(args)
    return policy, run_training(algo, args, resume=str(state) if state.exists() else None, config_path=recipe)["card"]


def evaluate_beta(policy: Path, beta: float, scenario: str, episodes: int, seed: int) -> dict:
    """The policy's evaluation on ``scenario`` with the same beta, kept next to the policy so
    that a second call only assembles the figure."""
    path = policy.with_name(f"{policy.stem}_{scenario}_{episodes}ep_seed{seed}.json")
    if path.exists():
        return json.loads(path.read_text())
    rec = evaluate(str(policy), load_city(scenario, beta=beta), episodes=episodes, seed=seed)
    path.write_text(json.dumps(rec))
    return rec


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--betas", type=float, nargs="+", default=list(BETAS))
    parser.add_argument("--recipe", default=RECIPE, help="A2C training config whose args every beta trains with")
    parser.add_argument("--episodes", type=int, default=None, help="macro training episodes per beta (default: the recipe's)")
    parser.add_argument("--eval-scenario", default="lux")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--runs", default="runs/beta_sweep_batched")
    parser.add_argument("--out", default="docs/studies")
    parser.add_argument("--train-only", action="store_true", help="train every beta, evaluate nothing")
    args = parser.parse_args()
    runs, out = Path(args.runs), Path(args.out)
    cards = {beta: train_beta(beta, runs, args.recipe, args.episodes) for beta in args.betas}  # all training first: cheap
    for beta, (policy, card) in cards.items():
        print(f"beta={beta:g}: {policy} ({card['episodes_trained']} episodes, {card['training_wall_s']} s, macro profit {card['profit_mean']:,.0f})", flush=True)
    if args.train_only:
        return
    rows = []
    for beta, (policy, card) in cards.items():
        rec = evaluate_beta(policy, beta, args.eval_scenario, args.eval_episodes, args.seed)
        trained = {"training_wall_s": card["training_wall_s"], "episodes_trained": card["episodes_trained"], "macro_profit": card["profit_mean"]}
        rows.append({"beta": beta, "policy": str(policy), **trained, "metrics": rec["metrics"]})
        print(f"beta={beta:g}:", {k: round(rec["metrics"][k]["mean"], 3) for k in COLUMNS}, flush=True)
    out.mkdir(parents=True, exist_ok=True)
    payload = {
        "scenario": args.eval_scenario, "trained_in": "lux_macro", "recipe": args.recipe, "episodes": args.eval_episodes,
        "seed": args.seed, "rows": rows,
    }  # fmt: skip
    (out / "beta_sweep.json").write_text(json.dumps(payload, indent=1))
    (out / "beta_sweep_table.md").write_text(table_markdown(payload))
    plot(rows, out / "beta_sweep.png")


def table_markdown(payload: dict) -> str:
    """Markdown table: mean ± std over the evaluation episodes of every column per beta."""
    lines = [
        "| beta | macro episodes | " + " | ".join(COLUMNS) + " |",
        "|---:|---:|" + "---:|" * len(COLUMNS),
    ]
    for r in payload["rows"]:
        cells = []
        for k in COLUMNS:
            m = r["metrics"][k]
            percent = k == "utilization"
            scale, digits = (100.0, 1) if percent else (1.0, 3 if "gini" in k else 2 if k == "wait_time" else 0)
            unit = "%" if percent else ""
            cells.append(f"{scale * m['mean']:,.{digits}f}{unit} ± {scale * m.get('std', 0.0):,.{digits}f}{unit}")
        lines.append(f"| {r['beta']:g} | {r.get('episodes_trained', '–'):,} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


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
