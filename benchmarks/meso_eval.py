"""Evaluate several policies on Luxembourg in SUMO meso, one ``evaluate --output`` file each.

One process for all of them, so SUMO's routing weights are read once (about 40 s) and the
shortest-path trees built by the first episodes serve the rest; a policy whose file already
exists is skipped, so an interrupted run resumes where it stopped. The files feed
``benchmarks/meso_table.py``.

    python benchmarks/meso_eval.py no-rebalancing mpc-oracle policies/a2c_gnn_lux.pt \
        --episodes 10 --seed 0 --out runs/meso_eval
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

from marl_amod.evaluation import evaluate, results_payload  # noqa: E402
from marl_amod.files import write_json  # noqa: E402
from marl_amod.scenario import load_city  # noqa: E402


def output_path(policy: str, out: Path, episodes: int, seed: int) -> Path:
    """Where one policy's record goes: its name (a checkpoint's stem), episodes and seed."""
    name = Path(policy).stem if policy.endswith(".pt") else policy
    return out / f"{name}_{episodes}ep_seed{seed}.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("policies", nargs="+", help="registered policy names or checkpoint .pt paths")
    parser.add_argument("--scenario", default="lux")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="runs/meso_eval")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    city = load_city(args.scenario)
    for policy in args.policies:
        path = output_path(policy, out, args.episodes, args.seed)
        if path.exists():
            print(f"{policy}: kept {path}", flush=True)
            continue
        start = time.perf_counter()
        record = evaluate(policy, city, args.episodes, args.seed)
        write_json(path, results_payload([record]))
        profit = record["metrics"]["profit"]
        print(f"{policy}: profit {profit['mean']:,.0f} ± {profit['std']:,.0f} in {time.perf_counter() - start:.0f} s -> {path}", flush=True)


if __name__ == "__main__":
    main()
