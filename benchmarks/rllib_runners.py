"""RLlib PPO on the synthetic city with 1 vs 2 env runners: env steps per second and wall time to a target.

One run per setting (same config, same seed), each on its own local Ray instance. Prints a markdown
table: Ray start + algorithm build, median iteration time and its sampling and learning parts
(RLlib's timers), env steps per second while sampling and over whole iterations (medians: the
machine may be shared), and the wall time (from before ``ray.init``) until the deterministic policy first reaches
``--target`` validation profit (equal distribution: about 8,266; native GNN A2C: about 8,841),
with the ratios of 2 runners to 1.

    python benchmarks/rllib_runners.py [--config configs/ppo_rllib/synthetic.yaml] [--target 8700] [--time-limit 240]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
from pathlib import Path

from marl_amod.integrations.rllib import load_rllib_config, train_rllib


def run(config: Path, runners: int, target: float, time_limit: float, eval_every: int) -> dict[str, float]:
    """One training run; numbers from its per-iteration history."""
    args = load_rllib_config(config).model_copy(
        update={
            "num_env_runners": runners, "target_profit": target, "time_limit_s": time_limit, "iterations": 10_000,
            "eval_every": eval_every, "final_eval_episodes": 1, "policy_out": "",
            "run_dir": tempfile.mkdtemp(prefix=f"rllib_runners_{runners}_", dir=Path("runs").resolve() if Path("runs").is_dir() else None),
        }
    )
    hist = train_rllib(args)["history"]
    first = hist[0]

    def med(key: str) -> float:  # medians, not means: the machine may be shared
        return statistics.median(h[key] for h in hist)

    hit = next((h for h in hist if h.get("eval/profit", -1e18) >= target), None)
    return {
        "runners": runners,
        "startup_s": first["wall_s"] - first["iter_s"],
        "iter_s": med("iter_s"),
        "sample_s": med("sample_s"),
        "learn_s": med("learn_s"),
        "sample_steps_per_s": med("env_steps_iter") / med("sample_s"),
        "env_steps_per_s": med("env_steps_iter") / med("iter_s"),
        "iterations": len(hist),
        "to_target_s": hit["wall_s"] if hit else float("nan"),
        "best_val_profit": max(h.get("eval/profit", float("-inf")) for h in hist),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", type=Path, default=Path("configs/ppo_rllib/synthetic.yaml"))
    p.add_argument("--target", type=float, default=8700.0)
    p.add_argument("--time-limit", type=float, default=240.0, help="per run; to_target_s is nan if not reached")
    p.add_argument("--eval-every", type=int, default=5)
    p.add_argument("--output", type=Path, default=None)
    a = p.parse_args()
    rows = [run(a.config, k, a.target, a.time_limit, a.eval_every) for k in (1, 2)]
    one, two = rows
    print(f"\nRLlib PPO, synthetic city, target validation profit {a.target:,.0f}\n")
    cols = [
        ("Ray start + build (s)", "startup_s", ".1f"), ("s / iteration", "iter_s", ".2f"), ("sampling s / iter", "sample_s", ".2f"),
        ("learning s / iter", "learn_s", ".2f"), ("env steps / s (sampling)", "sample_steps_per_s", ".0f"),
        ("env steps / s (training)", "env_steps_per_s", ".0f"), ("wall to target (s)", "to_target_s", ".0f"),
    ]
    print("| env runners | " + " | ".join(c[0] for c in cols) + " | iterations | best val profit |")
    print("|---" * (len(cols) + 3) + "|")
    for r in rows:
        print(f"| {r['runners']} | " + " | ".join(f"{r[k]:{f}}" for _, k, f in cols) + f" | {r['iterations']} | {r['best_val_profit']:,.0f} |")
    print("| ratio 2/1 | " + " | ".join(f"{two[k] / one[k]:.2f}" for _, k, _f in cols) + " | | |")
    if a.output:
        a.output.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
