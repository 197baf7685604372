"""Reward design, the paper's beta sweep: Graph-RL trained with trip cost c_ij = beta * tau_ij per
beta, evaluated on Luxembourg in SUMO meso; writes the figure and a table (with equity metrics).

Two training routes, both in the *macro* twin (``lux_macro`` with ``beta`` overridden):

* ``--route a2c``: A2C + GCN from scratch with the batched recipe of
  ``configs/a2c/lux_macro_batched.yaml`` (16 episodes in lockstep). On Luxembourg it stays at
  equal distribution for every beta (docs/studies/beta_sweep.md), so only the cost accounting moves.
* ``--route imitation``: MPC-Forecast, whose objective carries the same beta-scaled trip cost
  (so its rebalancing changes with beta), is rolled for ``--collect-episodes`` episodes on the
  training seeds, and the GCN actor is cloned from it with the BC recipe of
  ``configs/bc/lux_macro_mpc_forecast.yaml``; ``--refine RECIPE`` then continues with A2C from the
  clone (a config with the anti-forgetting options: kl_coef, action_concentration, critic_warmup).

Each policy is then evaluated in *meso* (``lux`` with the same beta, so it is scored with the cost
it was trained for) on the report seeds. Everything under ``--runs`` is reused (datasets,
clones, trainings, evaluations) and an interrupted A2C training resumes from its state, so a
second call only redraws what is missing. The figure and table hold every route with results
under its default runs folder.

    python benchmarks/beta_sweep.py                       # route a2c: train + evaluate + figure + table
    python benchmarks/beta_sweep.py --route imitation     # route imitation
    python benchmarks/beta_sweep.py --betas 0.1 0.5 --episodes 2000 --eval-episodes 2
"""

from __future__ import annotations

import argparse
import json
import os
from functools import partial
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import time  # noqa: E402

import numpy as np  # noqa: E402

from marl_amod.algos.common import state_path  # noqa: E402
from marl_amod.algos.registry import args_for, load_train_config, run_training  # noqa: E402
from marl_amod.config import read_config  # noqa: E402
from marl_amod.datasets import OfflineDataset, collect  # noqa: E402
from marl_amod.evaluation import evaluate  # noqa: E402
from marl_amod.policies import make_policy  # noqa: E402
from marl_amod.scenario import load_city  # noqa: E402

BETAS = (0.1, 0.2, 0.3, 0.5, 0.8, 1.2)
RECIPE = "configs/a2c/lux_macro_batched.yaml"
BC_RECIPE = "configs/bc/lux_macro_mpc_forecast.yaml"
RUNS = {"a2c": "runs/beta_sweep_batched", "imitation": "runs/beta_sweep_imitation"}
ROUTE_LABELS = {"a2c": "A2C from scratch", "imitation": "clone of MPC-Forecast", "imitation+a2c": "clone + A2C"}
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


def beta_scenario(beta: float, runs: Path, base: str = "lux_macro") -> Path:
    """A scenario file: ``base`` with ``beta`` overridden (what training and the expert see)."""
    tag = f"beta{beta:g}"
    runs.mkdir(parents=True, exist_ok=True)
    scenario = runs / f"{Path(base).stem}_{tag}.yaml"
    scenario.write_text(f"extends: {base}\nname: {Path(base).stem}_{tag}\nbeta: {beta}\n")
    return scenario


def train_a2c(
    beta: float,
    runs: Path,
    recipe: str,
    episodes: int | None,
    *,
    base: str = "lux_macro",
    tag: str = "a2c_gnn",
    init_actor: str = "",
    overrides: dict | None = None,
) -> tuple[Path, dict]:
    """Train (or reuse, or resume) A2C for ``beta`` with the recipe's args (from ``init_actor`` if
    given); returns its path and card."""
    policy = runs / f"{tag}_{Path(base).stem}_beta{beta:g}.pt"
    if policy.exists():
        return policy, json.loads(policy.with_suffix(".json").read_text())
    scenario = beta_scenario(beta, runs, base)
    raw = read_config(recipe)  # validated below with init_actor set (kl_coef needs one)
    algo = raw["algo"]
    values = {
        **raw.get("args", {}), **(overrides or {}), "scenario": str(scenario),
        "run_dir": str(runs / f"{tag}_beta{beta:g}" if init_actor else runs / f"beta{beta:g}"), "policy_out": str(policy),
        "init_actor": init_actor,
    }  # fmt: skip
    if episodes is not None:
        values["episodes"] = episodes
    args = args_for(algo, values, recipe)
    state = state_path(args)
    return policy, run_training(algo, args, resume=str(state) if state.exists() else None, config_path=recipe)["card"]


def train_beta(beta: float, runs: Path, recipe: str, episodes: int | None) -> tuple[Path, dict]:
    """Route a2c: A2C from scratch for ``beta``."""
    return train_a2c(beta, runs, recipe, episodes)


def imitate_beta(
    beta: float,
    runs: Path,
    *,
    base: str = "lux_macro",
    expert: str = "mpc-forecast",
    episodes: int = 40,
    seed: int = 0,
    bc_recipe: str = BC_RECIPE,
    overrides: dict | None = None,
) -> tuple[Path, dict]:
    """Route imitation: roll ``expert`` with ``beta`` for ``episodes`` training-seed episodes (kept
    as a dataset) and clone it with ``bc_recipe`` (``overrides`` on its args); returns the clone and
    its card, with the expert's mean training-episode profit and wall time added."""
    policy = runs / f"bc_gnn_{Path(base).stem}_beta{beta:g}.pt"
    if policy.exists():
        return policy, json.loads(policy.with_suffix(".json").read_text())
    scenario = beta_scenario(beta, runs, base)
    data_path = runs / f"{expert}_{Path(base).stem}_beta{beta:g}_{episodes}ep_seed{seed}.npz"
    collect_s = 0.0
    if not data_path.exists():
        city = load_city(str(scenario))
        start = time.perf_counter()
        collect(city, make_policy(expert, city), episodes=episodes, seed=seed).save(data_path)
        collect_s = time.perf_counter() - start
    data = OfflineDataset.load(data_path)
    algo, cfg = load_train_config(bc_recipe)
    values = {
        **cfg.model_dump(exclude_unset=True), **(overrides or {}), "scenario": str(scenario), "dataset": str(data_path),
        "run_dir": str(runs / f"bc_beta{beta:g}"), "policy_out": str(policy),
    }  # fmt: skip
    card = run_training(algo, args_for(algo, values, bc_recipe), config_path=bc_recipe)["card"]
    card["expert"] = {
        "policy": expert,
        "episodes": episodes,
        "seed": seed,
        "profit_mean": data.meta["episode_profit_mean"],
        "collect_wall_s": round(collect_s, 1),
    }
    policy.with_suffix(".json").write_text(json.dumps(card, indent=1))
    return policy, card


def evaluate_beta(policy: Path, beta: float, scenario: str, episodes: int, seed: int) -> dict:
    """The policy's evaluation on ``scenario`` with the same beta, kept next to the policy so
    that a second call only assembles the figure."""
    path = policy.with_name(f"{policy.stem}_{scenario}_{episodes}ep_seed{seed}.json")
    if path.exists():
        return json.loads(path.read_text())
    rec = evaluate(str(policy), load_city(scenario, beta=beta), episodes=episodes, seed=seed)
    path.write_text(json.dumps(rec))
    return rec


def train_route(args: argparse.Namespace, beta: float, runs: Path) -> tuple[Path, dict]:
    """The policy for ``beta`` by ``args.route`` (and ``--refine``): trained, reused or resumed."""
    if args.route == "a2c":
        return train_a2c(beta, runs, args.recipe, args.episodes, base=args.train_scenario)
    clone, card = imitate_beta(
        beta, runs, base=args.train_scenario, expert=args.expert, episodes=args.collect_episodes, seed=args.seed,
        bc_recipe=args.bc_recipe, overrides=args.bc_overrides,
    )  # fmt: skip
    if not args.refine:
        return clone, card
    policy, refined = train_a2c(
        beta, runs, args.refine, args.episodes, base=args.train_scenario, tag="a2c_from_clone", init_actor=str(clone)
    )
    return policy, {**refined, "expert": card["expert"], "clone_profit_mean": card["profit_mean"]}


def route_row(beta: float, policy: Path, card: dict, rec: dict) -> dict:
    """One table/figure row: what trained the policy and its meso metrics."""
    trained = {
        "training_wall_s": card["training_wall_s"],
        "episodes_trained": card["episodes_trained"],
        "macro_profit": card["profit_mean"],
    }
    if "expert" in card:
        trained["expert"] = card["expert"]
    return {"beta": beta, "policy": str(policy), **trained, "metrics": rec["metrics"]}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--route",
        choices=sorted(RUNS),
        default="a2c",
        help="a2c: A2C from scratch; imitation: clone of the expert with the same beta",
    )
    parser.add_argument("--betas", type=float, nargs="+", default=list(BETAS))
    parser.add_argument("--train-scenario", default="lux_macro", help="the scenario trained in (beta overridden)")
    parser.add_argument("--recipe", default=RECIPE, help="route a2c: A2C training config whose args every beta trains with")
    parser.add_argument("--episodes", type=int, default=None, help="A2C training episodes per beta (default: the recipe's)")
    parser.add_argument("--expert", default="mpc-forecast", help="route imitation: the policy cloned")
    parser.add_argument(
        "--collect-episodes", type=int, default=40, help="route imitation: expert episodes per beta (training seeds)"
    )
    parser.add_argument("--bc-recipe", default=BC_RECIPE, help="route imitation: behaviour-cloning config")
    parser.add_argument("--bc-updates", type=int, default=None, help="route imitation: BC updates (default: the recipe's)")
    parser.add_argument("--refine", default="", help="route imitation: A2C config continuing from each clone (empty: none)")
    parser.add_argument("--eval-scenario", default="lux")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--runs", default=None, help="where policies and evaluations are kept (default: the route's)")
    parser.add_argument("--out", default="docs/studies")
    parser.add_argument("--train-only", action="store_true", help="train every beta, evaluate nothing")
    args = parser.parse_args(argv)
    args.bc_overrides = {"updates": args.bc_updates} if args.bc_updates else {}
    runs, out = Path(args.runs or RUNS[args.route]), Path(args.out)
    cards = {beta: train_route(args, beta, runs) for beta in args.betas}  # all training first: cheap
    for beta, (policy, card) in cards.items():
        print(
            f"beta={beta:g}: {policy} ({card['episodes_trained']} episodes, {card['training_wall_s']} s, macro profit {card['profit_mean']:,.0f})",
            flush=True,
        )
    if args.train_only:
        return {}
    rows = []
    for beta, (policy, card) in cards.items():
        rec = evaluate_beta(policy, beta, args.eval_scenario, args.eval_episodes, args.seed)
        rows.append(route_row(beta, policy, card, rec))
        print(f"beta={beta:g}:", {k: round(rec["metrics"][k]["mean"], 3) for k in COLUMNS}, flush=True)
    out.mkdir(parents=True, exist_ok=True)
    routes = json.loads((out / "beta_sweep.json").read_text()).get("routes", {}) if (out / "beta_sweep.json").exists() else {}
    routes[args.route + ("+a2c" if args.refine else "")] = {
        "trained_in": args.train_scenario, "recipe": args.recipe if args.route == "a2c" else args.bc_recipe,
        "refine": args.refine, "rows": rows,
    }  # fmt: skip
    payload = {"scenario": args.eval_scenario, "episodes": args.eval_episodes, "seed": args.seed, "routes": routes}
    (out / "beta_sweep.json").write_text(json.dumps(payload, indent=1))
    (out / "beta_sweep_table.md").write_text(table_markdown(payload))
    plot(payload, out / "beta_sweep.png")
    return payload


def table_markdown(payload: dict) -> str:
    """Markdown table: mean ± std over the evaluation episodes of every column per route and beta."""
    lines = [
        "| route | beta | trained on (macro) | " + " | ".join(COLUMNS) + " |",
        "|---|---:|---:|" + "---:|" * len(COLUMNS),
    ]
    for route, block in payload["routes"].items():
        for r in block["rows"]:
            cells = []
            for k in COLUMNS:
                m = r["metrics"][k]
                percent = k == "utilization"
                scale, digits = (100.0, 1) if percent else (1.0, 3 if "gini" in k else 2 if k == "wait_time" else 0)
                unit = "%" if percent else ""
                cells.append(f"{scale * m['mean']:,.{digits}f}{unit} ± {scale * m.get('std', 0.0):,.{digits}f}{unit}")
            lines.append(f"| {route} | {r['beta']:g} | {trained_on(r)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def trained_on(row: dict) -> str:
    """What the row's policy learnt from: the expert's episodes it was cloned from, A2C's episodes."""
    parts = []
    if "expert" in row:
        parts.append(f"BC on {row['expert']['episodes']:,} {row['expert']['policy']} ep.")
    if row.get("episodes_trained") or not parts:
        parts.append(f"{row.get('episodes_trained', 0):,} A2C ep.")
    return " + ".join(parts)


def _errorbars(ax, key: str, *, rows: list[dict], **kw) -> None:
    """Mean ± std of metric ``key`` against beta."""
    beta = np.array([r["beta"] for r in rows])
    m = np.array([r["metrics"][key]["mean"] for r in rows])
    s = np.array([r["metrics"][key].get("std", 0.0) for r in rows])
    ax.errorbar(beta, m, yerr=s, capsize=3, **kw)


def plot(payload: dict, path: Path) -> None:
    """The paper's figure: top profit, revenue, rebalancing cost; bottom waiting time, utilisation;
    one line style per route (solid: the first, dashed: the second)."""
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9.5, 7.5), sharex=True)
    twin = bottom.twinx()
    styles = ("-", "--", ":")
    for (route, block), style in zip(payload["routes"].items(), styles, strict=False):
        rows, label = block["rows"], ROUTE_LABELS.get(route, route)
        bars = partial(_errorbars, rows=rows, linestyle=style)
        for key, name, color in (
            ("profit", "profit", "tab:blue"),
            ("revenue", "revenue", "tab:orange"),
            ("rebalancing_cost", "rebalancing cost", "tab:green"),
        ):
            bars(top, key, marker="o", color=color, label=f"{name} ({label})")
        bars(bottom, "wait_time", marker="o", color="tab:red", label=f"waiting time ({label})")
        bars(twin, "utilization", marker="s", color="tab:purple", label=f"utilisation ({label})")
    top.set_ylabel("money per episode")
    top.set_ylim(top=1.5 * top.get_ylim()[1])  # room above the curves for one legend column per route
    top.legend(fontsize="x-small", ncol=len(payload["routes"]), loc="upper center")
    bottom.set_ylabel("waiting time (min)")
    bottom.set_xlabel(r"$\beta$ (trip cost $c_{ij} = \beta\,\tau_{ij}$)")
    twin.set_ylabel("fleet utilisation")
    lines = bottom.get_legend_handles_labels()[0] + twin.get_legend_handles_labels()[0]
    labels = [ln.get_label() for ln in lines]  # below the panel: the curves fill it
    bottom.legend(lines, labels, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, fontsize="x-small")
    fig.suptitle("Graph-RL on Luxembourg (SUMO meso) vs trip-cost weight")
    fig.tight_layout()
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    main()
