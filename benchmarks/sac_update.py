"""CPU milliseconds of one SAC gradient update, part by part (the batched, dense-graph path).

Builds the learner ``marl_amod.algos.sac.Learner`` exactly as ``train`` does (same networks,
optimisers and precision), fills a replay buffer with random transitions of the city's shapes
(features on the observations' scale, Dirichlet actions) and times ``--updates`` calls of the real
``Learner.update`` after ``--skip`` warm-up ones. ``update`` marks the end of each part, so the
table splits one update into: the actor's two passes (policy sample with a graph, the target's
next actions without), the target critics, the critic loss (forward + backward), the critic's
clipping and Adam step, the policy loss (critic forward + backward into the actor), the actor's
clipping and Adam step with Polyak averaging, and the replay sample. CPU time of this process,
one torch thread: on a shared machine it varies less than wall time.

    python benchmarks/sac_update.py [--city nyc_brooklyn] [--settings h64 h256 h256-bf16]
        [--batch-size 100] [--updates 300] [--compile] [--ref REV [--rounds 10]] [--json out.json]

``--compile`` wraps the actor and both critics in ``torch.compile`` (inductor) first, to compare
with eager PyTorch (not used by training: slower here, see docs/studies/sac_update.md).

``--ref REV`` also times ``marl_amod/algos/sac.py`` as of git revision REV (the rest of the
package from this tree) in the same process, alternating the two in ``--rounds`` rounds, and
prints the ratio of the totals: on a loaded machine only such side-by-side ratios compare.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from types import ModuleType

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

from marl_amod.algos import common as C  # noqa: E402
from marl_amod.algos import sac  # noqa: E402
from marl_amod.algos.sac import Replay  # noqa: E402
from marl_amod.env.features import n_features  # noqa: E402
from marl_amod.scenario import load_city  # noqa: E402

# label -> (hidden units, precision)
SETTINGS = {"h64": (64, "fp32"), "h256": (256, "fp32"), "h256-bf16": (256, "bf16"), "h64-bf16": (64, "bf16")}
PARTS = ["actor", "target critics", "critic loss", "critic step", "policy loss", "actor step, Polyak", "replay sample"]


def filled_replay(n: int, f: int, rows: int, seed: int) -> Replay:
    """``rows`` random transitions of N regions with F features (scaled like observations: up to ~40)."""
    g = torch.Generator().manual_seed(seed)
    scale = torch.linspace(1, 40, f)
    buffer = Replay(rows)
    buffer.add(
        rows, x=torch.rand(rows, n, f, generator=g) * scale, action=torch.distributions.Dirichlet(torch.ones(rows, n)).sample(),
        reward=torch.randn(rows, generator=g), done=torch.zeros(rows), next_x=torch.rand(rows, n, f, generator=g) * scale,
    )  # fmt: skip
    return buffer


def sac_at(rev: str) -> ModuleType:
    """``marl_amod/algos/sac.py`` as of git revision ``rev``, imported beside this tree's."""
    root = Path(__file__).resolve().parent.parent
    source = subprocess.run(["git", "-C", str(root), "show", f"{rev}:marl_amod/algos/sac.py"], capture_output=True, text=True, check=True).stdout
    with tempfile.TemporaryDirectory(prefix="sac-ref-") as tmp:  # read once, by the import
        path = Path(tmp) / "sac_ref.py"
        path.write_text(source)
        spec = importlib.util.spec_from_file_location("sac_ref", path)
        module = importlib.util.module_from_spec(spec)
        sys.modules["sac_ref"] = module  # pydantic resolves the Args annotations through it
        spec.loader.exec_module(module)
    return module


class UpdateTimer:
    """One learner built as ``train`` builds it (``module``: this tree's sac or a reference's) on
    a replay of random transitions; :meth:`run` times its updates part by part and accumulates."""

    def __init__(self, module: ModuleType, city_name: str, hidden: int, precision: str, batch: int, compile_nets: bool) -> None:
        torch.manual_seed(0)
        self.city = load_city(city_name)
        args = module.Args(scenario=city_name, hidden=hidden, precision=precision, batch_size=batch, num_envs=16, threads=1, policy_out="")
        self.learner = module.Learner(args, self.city, C.make_graph(self.city, args))
        if compile_nets:
            lr = self.learner
            lr.actor, lr.critic, lr.critic_targ = (torch.compile(m) for m in (lr.actor, lr.critic, lr.critic_targ))
        self.buffer = filled_replay(self.city.n_regions, n_features(args.lookahead), max(2000, batch), seed=0)
        self.batch, self.gen = batch, torch.Generator().manual_seed(0)
        self.spent: dict[str, float] = defaultdict(float)
        self.updates = 0

    def run(self, updates: int, record: bool = True) -> None:
        clock = [time.process_time()]
        spent: dict[str, float] = defaultdict(float)

        def mark(part: str) -> None:
            now = time.process_time()
            spent[part] += now - clock[0]
            clock[0] = now

        for _ in range(updates):
            clock[0] = time.process_time()
            b = self.buffer.sample(self.batch, self.gen)
            mark("replay sample")
            self.learner.update(b, mark)
        if record:
            for part, s in spent.items():
                self.spent[part] += s
            self.updates += updates

    def ms(self) -> dict[str, float]:
        """CPU ms per update of each part, and their total."""
        ms = {part: self.spent[part] / self.updates * 1e3 for part in PARTS}
        ms["total"] = sum(ms.values())
        return ms


def time_updates(city_name: str, hidden: int, precision: str, batch: int, updates: int, skip: int, compile_nets: bool,
                 ref: ModuleType | None = None, rounds: int = 1) -> dict[str, dict[str, float]]:
    """CPU ms per update of each part for this tree (``"new"``) and, with ``ref``, the reference
    (``"ref"``), their timed updates split into ``rounds`` alternating rounds."""
    timers = {"new": UpdateTimer(sac, city_name, hidden, precision, batch, compile_nets)}
    if ref is not None:
        timers = {"ref": UpdateTimer(ref, city_name, hidden, precision, batch, compile_nets), **timers}
    for t in timers.values():
        t.run(skip, record=False)
    for r in range(rounds):
        for t in timers.values():
            t.run(updates // rounds + (r < updates % rounds))
    return {k: t.ms() for k, t in timers.items()}


def table(results: dict[str, dict[str, float]]) -> str:
    labels = list(results)
    lines = ["| part of the update | " + " | ".join(labels) + " |", "|---|" + "---:|" * len(labels)]
    for part in [*PARTS, "total"]:
        cells = [f"{results[label][part]:.2f}" for label in labels]
        if part == "total":
            lines.append("| **total** | " + " | ".join(f"**{c}**" for c in cells) + " |")
        else:
            lines.append(f"| {part} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--city", default="nyc_brooklyn")
    parser.add_argument("--settings", nargs="+", default=["h64", "h256", "h256-bf16"], choices=list(SETTINGS))
    parser.add_argument("--batch-size", type=int, default=100)
    parser.add_argument("--updates", type=int, default=300, help="timed updates per setting")
    parser.add_argument("--skip", type=int, default=50, help="warm-up updates before timing")
    parser.add_argument("--compile", action="store_true", help="torch.compile the actor and critics first (for comparison)")
    parser.add_argument("--ref", default=None, help="git revision whose sac.py to time alongside, alternating")
    parser.add_argument("--rounds", type=int, default=10, help="alternating rounds with --ref")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    C.retain_freed_memory()  # as train() does
    ref = sac_at(args.ref) if args.ref else None
    results = {}
    for label in args.settings:
        hidden, precision = SETTINGS[label]
        timed = time_updates(args.city, hidden, precision, args.batch_size, args.updates, args.skip, args.compile, ref, args.rounds if ref else 1)
        if ref is None:
            results[label] = timed["new"]
        else:
            results[f"{label} {args.ref}"], results[label] = timed["ref"], timed["new"]
            print(f"{label}: {timed['ref']['total']:.2f} ms at {args.ref}, {timed['new']['total']:.2f} ms now: "
                  f"{timed['ref']['total'] / timed['new']['total']:.3f}x", flush=True)
        print(f"{label}: {results[label]['total']:.2f} ms per update", flush=True)
    md = table(results)
    print(md)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        payload = {"city": args.city, "batch_size": args.batch_size, "updates": args.updates, "skip": args.skip, "compile": args.compile, "ref": args.ref,
                   "torch": torch.__version__, "load_average": os.getloadavg(), "ms_per_update": results, "markdown": md}  # fmt: skip
        args.json.write_text(json.dumps(payload, indent=2) + "\n")


if __name__ == "__main__":
    main()
