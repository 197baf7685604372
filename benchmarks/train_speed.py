"""Training throughput of A2C and SAC, this tree against an earlier git ref, side by side in one run.

For every algorithm, city and setting the trainer runs for ``--seconds`` of wall time in a fresh
subprocess, once with this tree's ``marl_amod`` and once with the ref's (``git archive`` of the
ref into a temporary folder, put first on ``PYTHONPATH``; the same worker code drives both through
the public ``ALGOS`` registry, so the ref must have ``marl_amod.algos``). Runs alternate between
the two trees so a machine whose load changes affects both alike. Reported, after the first
update (start-up, imports and warm-up excluded):

* ``episodes/s`` and ``env steps/s`` (one control step of one episode; B lockstep episodes count B);
* ``updates/s``: gradient steps (one critic and one actor step; counted at the optimisers);
* the ratios this tree / ref, in wall time and in the worker's CPU time (``ratio CPU``: on a
  loaded machine a process's CPU seconds vary less than its wall seconds).

Settings compare like with like: the same network, batch size and updates per transition; the
new tree runs ``--num-envs`` episodes in lockstep (the batched simulator and dense graph layers),
the ref one at a time, and a setting may add options only the new tree has (``sac h256 bf16``:
the bfloat16 update). Both run with one torch thread.

    python benchmarks/train_speed.py --ref main [--seconds 30] [--cities nyc_brooklyn synthetic]
        [--json docs/results/train_speed.json]

The JSON holds every measurement and the markdown table that is printed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

_SAC = {"batch_size": 100, "warmup_steps": 100, "updates_per_step": 1}
# label -> (algo, args shared by both trees, args of the new tree only); the new tree also gets
# num_envs (and no critic_time: the same networks)
SETTINGS: dict[str, tuple[str, dict[str, Any], dict[str, Any]]] = {
    "a2c": ("a2c", {"hidden": 32, "episodes_per_update": 16}, {}),  # the new tree: 16 lockstep episodes = one update
    "sac h256": ("sac", {"hidden": 256, **_SAC}, {}),
    "sac h256 bf16": ("sac", {"hidden": 256, **_SAC}, {"precision": "bf16"}),
    "sac h64": ("sac", {"hidden": 64, **_SAC}, {}),
}
# 400 regions: a small replay buffer (each transition holds 2 x 400 x 13 floats), twice the time
# (an episode of the ref takes seconds), and SAC with 256 hidden units only with --all
LARGE = {"synthetic_large"}


class _Stop(Exception):
    """Raised inside the trainer when the measured time is up (trainers check their own limit
    only between updates, which a batched SAC run may not reach in a short window)."""


def worker(spec: dict[str, Any]) -> dict[str, Any]:
    """Run one trainer for ``spec['seconds']`` and return its rates (this process's marl_amod).

    Env steps are counted where every trainer takes them (``FleetSystem.step``, and
    ``BatchFleetSystem.step`` as B steps where the tree has it) and gradient steps at the Adam
    optimisers (one update = a critic and an actor step), each with its time. The window starts
    at the first update when there is one before the end (SAC's warm-up excluded), else at the
    first env step (``from_start``), and ends at the last event.
    """
    import torch

    from marl_amod.algos.registry import ALGOS
    from marl_amod.scenario import load_city
    from marl_amod.system import FleetSystem

    torch.set_num_threads(1)
    events: dict[str, list[tuple[float, int, float]]] = {"env": [], "opt": []}  # (wall, n, CPU seconds)
    deadline = [float("inf")]

    def tick(kind: str, n: int) -> None:
        now = time.perf_counter()
        events[kind].append((now, n, time.process_time()))
        if now > deadline[0]:
            raise _Stop

    def counting(cls: type, name: str, kind: str, size: Any) -> None:
        original = getattr(cls, name)

        def wrapped(self: Any, *a: Any, **k: Any) -> Any:
            out = original(self, *a, **k)
            tick(kind, size(self))
            return out

        setattr(cls, name, wrapped)

    counting(torch.optim.Adam, "step", "opt", lambda self: 1)
    counting(FleetSystem, "step", "env", lambda self: 1)
    try:
        from marl_amod.batch_system import BatchFleetSystem

        counting(BatchFleetSystem, "step", "env", lambda self: self.num_envs)
    except ImportError:  # the ref has no batched simulator
        pass
    entry = ALGOS[spec["algo"]]
    horizon = load_city(spec["city"]).horizon
    with tempfile.TemporaryDirectory() as run_dir:
        args = entry.args(
            scenario=spec["city"], episodes=10**7, eval_every=10**8, eval_episodes=1, final_eval_episodes=1,
            run_dir=run_dir, policy_out="", threads=1, **spec["args"],
        )
        deadline[0] = time.perf_counter() + spec["seconds"]
        try:
            entry.train(args)
        except _Stop:
            pass
    env, opt = events["env"], events["opt"]
    if not env:
        return {"episodes_per_s": None, "env_steps_per_s": None, "updates_per_s": None, "episodes_per_cpu_s": None, "timed_s": 0.0}
    from_start = len(opt) < 4  # fewer than two updates: no steady window after the first one
    first = env[0] if from_start else opt[0]
    last = max(env[-1], opt[-1]) if opt else env[-1]
    t0, dt, cpu_s = first[0], last[0] - first[0], last[2] - first[2]
    steps = sum(n for t, n, _ in env if t >= t0) - (env[0][1] if from_start else 0)
    per_update = 2  # one critic and one actor optimiser step (no auto_entropy here)
    updates = (len([1 for t, _, _ in opt if t > t0]) / per_update) if opt else 0.0
    return {
        "episodes_per_s": steps / (horizon - 1) / dt,
        "env_steps_per_s": steps / dt,
        "updates_per_s": updates / dt,
        "episodes_per_cpu_s": steps / (horizon - 1) / cpu_s,
        "timed_s": dt,
        "cpu_s": cpu_s,
        "env_steps": steps,
        "updates": updates,
        "from_start": from_start,  # True: start-up and the first update included (slow cells)
    }


def run_worker(tree: Path, spec: dict[str, Any]) -> dict[str, Any]:
    """``worker(spec)`` in a subprocess that imports ``marl_amod`` from ``tree``."""
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    out = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec)],
        env=env, capture_output=True, text=True, cwd=tempfile.gettempdir(), check=False,
    )
    if out.returncode != 0:
        raise RuntimeError(f"worker failed in {tree} for {spec}:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def export_ref(ref: str, dest: Path) -> str:
    """The ref's files (``git archive``) under ``dest``; returns the commit id."""
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--verify", f"{ref}^{{commit}}"], capture_output=True, text=True, check=True).stdout.strip()
    archive = dest / "ref.tar"
    subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", "-o", str(archive), commit], check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(dest / "tree", filter="data")
    return commit


def fmt(x: float | None, digits: int = 1) -> str:
    return "n/a" if x is None else f"{x:,.{digits}f}"


def table(rows: list[dict[str, Any]], num_envs: int) -> str:
    lines = [
        f"| setting | city | episodes/s ref | episodes/s new (B={num_envs}) | ratio | ratio CPU | env steps/s new | updates/s ref | updates/s new | ratio |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]

    def ratio(new: dict[str, Any], old: dict[str, Any], key: str) -> float | None:
        return new[key] / old[key] if old.get(key) and new.get(key) else None

    for r in rows:
        old, new = r["ref"], r["new"]
        lines.append(
            f"| {r['setting']} | {r['city']} | {fmt(old['episodes_per_s'], 2)} | {fmt(new['episodes_per_s'], 2)} "
            f"| {fmt(ratio(new, old, 'episodes_per_s'), 2)}x | {fmt(ratio(new, old, 'episodes_per_cpu_s'), 2)}x "
            f"| {fmt(new['env_steps_per_s'], 0)} | {fmt(old['updates_per_s'], 2)} | {fmt(new['updates_per_s'], 2)} "
            f"| {fmt(ratio(new, old, 'updates_per_s'), 2)}x |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ref", default="main", help="git ref of the implementation to compare against")
    parser.add_argument("--cities", nargs="+", default=["nyc_brooklyn", "synthetic", "synthetic_large"])
    parser.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    parser.add_argument("--seconds", type=float, default=30.0, help="wall seconds per trainer run")
    parser.add_argument("--num-envs", type=int, default=16, help="lockstep episodes of the new tree")
    parser.add_argument("--json", type=Path, default=None, help="write the measurements and table here")
    parser.add_argument("--all", action="store_true", help="also SAC h256 on the 400-region city (slow)")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        commit = export_ref(args.ref, Path(tmp))
        ref_tree = Path(tmp) / "tree"
        for setting in args.settings:
            algo, shared, new_only = SETTINGS[setting]
            for city in args.cities:
                if city in LARGE and setting.startswith("sac h256") and not args.all:
                    continue
                seconds = args.seconds * (2 if city in LARGE else 1)
                extra = {"buffer_size": 2000} if algo == "sac" and city in LARGE else {}
                spec = {"algo": algo, "city": city, "seconds": seconds, "args": {**shared, **extra}}
                new_args = {**spec["args"], **new_only, "num_envs": args.num_envs}
                if algo == "a2c":  # whole lockstep batches per update, as many episodes per update as the ref
                    new_args["episodes_per_update"] = max(shared["episodes_per_update"], args.num_envs)
                ref = run_worker(ref_tree, spec)
                new = run_worker(ROOT, {**spec, "args": new_args})
                rows.append({"setting": setting, "algo": algo, "city": city, "args": spec["args"], "new_args": new_args, "ref": ref, "new": new})
                print(f"{setting:9s} {city:16s} ref {fmt(ref['episodes_per_s'], 2)} ep/s  new {fmt(new['episodes_per_s'], 2)} ep/s", flush=True)
    md = table(rows, args.num_envs)
    print(md)
    if args.json:
        result = {
            "ref": args.ref, "ref_commit": commit, "seconds": args.seconds, "num_envs": args.num_envs, "torch_threads": 1,
            "load_average": os.getloadavg(), "rows": rows, "markdown": md,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
