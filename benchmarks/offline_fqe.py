"""Offline policy selection by fitted Q evaluation (FQE) on the benchmark's Brooklyn datasets.

    python benchmarks/offline_fqe.py --workers 2      # datasets collected into runs/fqe/ where missing, then every fit
    python benchmarks/offline_fqe.py --replot         # the page from docs/offline/fqe.json, evaluating nothing

The offline table's policies were chosen among checkpoints on validation episodes in the env
(``keep: best``). Could the dataset alone have chosen? For each dataset row of
``docs/offline/table.json`` (INF, DTV, PROP, MPC-Forecast, noisy PROP) this collects the dataset
again (the same collection seeds as the training data: ``marl-amod datasets``; MPC-Forecast's 3,000
episodes in pieces of 300), then FQE-scores (``marl_amod.fqe``, its defaults, seed 0) the logged
behaviour, the row's BC, IQL and CQL policies and the online SAC policy, and sets the estimates
beside the report profits the table holds (10 episodes, seed 0). FQE counts the profit of the
decisions; the first dispatch, before any decision, is the same for every policy, so it is added
from the report episodes (their mean first-dispatch profit) to put both columns in one unit.
It prints, and writes to ``docs/offline/fqe.md`` and ``fqe.json``: each row's policies by both
measures, whether FQE picks the row's best offline policy, and the rank correlation.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
TABLE = ROOT / "docs" / "offline" / "table.json"
OUT_JSON, OUT_MD = ROOT / "docs" / "offline" / "fqe.json", ROOT / "docs" / "offline" / "fqe.md"
DATA_DIR = Path("runs/fqe")
SAC = "policies/sac_gnn_nyc_brooklyn_fast.pt"
BEHAVIOUR = {"inf": ("inf", 0.0), "dtv": ("dtv", 0.0), "prop": ("prop", 0.0), "mpc_forecast": ("mpc-forecast", 0.0), "prop_noise": ("prop", 0.02)}
PIECE = 300  # episodes per collection job


def collect_piece(policy: str, noise: float, first: int, episodes: int, out: str) -> str:
    """Episodes ``first``..``first + episodes - 1`` of the behaviour's collection (seed 0), saved to ``out``."""
    from marl_amod.datasets import collect
    from marl_amod.policies import make_policy
    from marl_amod.scenario import load_city

    city = load_city("nyc_brooklyn")
    collect(city, make_policy(policy, city), episodes=episodes, seed=0, noise=noise, first_episode=first).save(out)
    return out


def fit(policy: str | None, dataset: str, updates: int) -> dict[str, Any]:
    from marl_amod import fqe

    start = time.perf_counter()
    got = fqe.estimate(policy, dataset, "nyc_brooklyn", fqe.FQESettings(updates=updates))
    return got.to_dict() | {"wall_s": round(time.perf_counter() - start, 1)}


def first_dispatch(episodes: int, seed: int) -> float:
    """The report episodes' mean profit of the first dispatch (before any decision: every policy's alike)."""
    from marl_amod.evaluation import episode_seeds
    from marl_amod.scenario import load_city
    from marl_amod.system import FleetSystem

    system = FleetSystem(load_city("nyc_brooklyn"))
    return float(np.mean([system.reset(episode_seeds(seed, k)[0]).reward for k in range(episodes)]))


def run(workers: int, updates: int, only: list[str] | None = None) -> dict[str, Any]:
    from marl_amod.datasets import OfflineDataset, merge

    table = json.loads(TABLE.read_text())
    table["rows"] = [r for r in table["rows"] if not only or r["dataset"] in only]
    DATA_DIR.mkdir(parents=True, exist_ok=True)
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
    pieces: dict[str, list[Any]] = {}
    for row in table["rows"]:
        name, (policy, noise) = row["dataset"], BEHAVIOUR[row["dataset"]]
        if not (DATA_DIR / f"{name}.npz").is_file():
            starts = range(0, row["episodes"], PIECE)
            pieces[name] = [pool.submit(collect_piece, policy, noise, k, min(PIECE, row["episodes"] - k), str(DATA_DIR / f"{name}_{k}.npz")) for k in starts]
    for name, futures in pieces.items():
        parts = [OfflineDataset.load(f.result()) for f in futures]
        (merge(parts) if len(parts) > 1 else parts[0]).save(DATA_DIR / f"{name}.npz")
        print(f"collected {name}: {sum(len(p) for p in parts)} transitions", flush=True)
    jobs = {}
    for row in table["rows"]:
        path = str(DATA_DIR / f"{row['dataset']}.npz")
        named = {"behaviour": None, **{algo: row[algo]["policy"] for algo in ("bc", "iql", "cql")}, "sac (online)": SAC}
        for label, policy in named.items():
            jobs[(row["dataset"], label)] = pool.submit(fit, policy, path, updates)
    offset = first_dispatch(table["evaluation"]["episodes"], table["evaluation"]["seed"])
    rows = []
    for row in table["rows"]:
        truth = {"behaviour": row["behaviour"]["mean"], **{a: row[a]["mean"] for a in ("bc", "iql", "cql")}, "sac (online)": row["sac_online"]["mean"]}
        got = {label: jobs[(row["dataset"], label)].result() for label in truth}
        rows.append({"dataset": row["dataset"], "episodes": row["episodes"],
                     "policies": {label: {"report": truth[label], "fqe": got[label]["profit"] + offset, **got[label]} for label in truth}})  # fmt: skip
        print(f"{row['dataset']}: " + ", ".join(f"{k} {v['fqe']:,.0f} (report {v['report']:,.0f})" for k, v in rows[-1]["policies"].items()), flush=True)
    pool.shutdown()
    return {"scenario": "nyc_brooklyn", "first_dispatch": offset, "evaluation": table["evaluation"], "updates": updates, "rows": rows}


def spearman(a: list[float], b: list[float]) -> float:
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1])


def page(result: dict[str, Any]) -> str:
    """The markdown of the study: one table, then what it says."""
    lines = ["<!-- python benchmarks/offline_fqe.py -->",
             f"FQE estimates (`marl_amod.fqe`, seed 0, {result['updates']:,} updates) from each dataset alone, beside the report profit (nyc_brooklyn, "
             f"{result['evaluation']['episodes']} episodes, seed {result['evaluation']['seed']}); both in k$, the FQE estimate plus the report "
             f"episodes' first dispatch ({result['first_dispatch']:,.0f} $, the same for every policy).", "",
             "| dataset | policy | report | FQE | FQE - report |", "|---|---|---|---|---|"]  # fmt: skip
    picks, corr = [], []
    for row in result["rows"]:
        pol = row["policies"]
        for label, v in pol.items():
            lines.append(f"| {row['dataset']} ({row['episodes']} ep.) | {label} | {v['report'] / 1e3:.2f} | {v['fqe'] / 1e3:.2f} | {(v['fqe'] - v['report']) / 1e3:+.2f} |")
        offline = ("bc", "iql", "cql")
        best_true = max(offline, key=lambda a: pol[a]["report"])
        best_fqe = max(offline, key=lambda a: pol[a]["fqe"])
        picks.append((row["dataset"], best_true, best_fqe, pol[best_true]["report"] - pol[best_fqe]["report"]))
        corr.append((row["dataset"], spearman([v["report"] for v in pol.values()], [v["fqe"] for v in pol.values()])))
    lines += ["", "| dataset | best offline policy (report) | FQE's pick | report profit lost by FQE's pick | rank correlation, all five |",
              "|---|---|---|---|---|"]  # fmt: skip
    for (name, t, f, lost), (_, rho) in zip(picks, corr, strict=True):
        lines.append(f"| {name} | {t} | {f} | {lost / 1e3:.2f}k | {rho:+.2f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=1, help="processes (collection pieces and fits run side by side)")
    parser.add_argument("--updates", type=int, default=3000, help="FQE regression steps per policy")
    parser.add_argument("--only", nargs="*", help="these dataset rows only (a smoke run: writes nothing under docs/)")
    parser.add_argument("--replot", action="store_true", help="rewrite the page from docs/offline/fqe.json")
    args = parser.parse_args()
    result = json.loads(OUT_JSON.read_text()) if args.replot else run(args.workers, args.updates, args.only)
    if args.only:
        print(page(result))
        return
    if not args.replot:
        OUT_JSON.write_text(json.dumps(result, indent=1))
    text = page(result)
    OUT_MD.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
