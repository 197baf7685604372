"""Diagnostics of the meta-policy (docs/meta/README.md): the imitation gap, K, the special event.

* ``gap``: on training cities, the cross-entropy of the policy's Dirichlet mean above the labels'
  own entropy, on MPC-Forecast's states (the last 8 stored demonstrations) and on the states
  the policy reaches itself (8 episodes it drives as deployed, labelled by MPC-F: a DAgger
  collection on streams of their own). Tells compounding error from under-fit.
* ``k``: the profit gap to MPC-Oracle on the held-out cities (report episodes, the tables'
  MPC-Oracle rows) for each number K of adaptation episodes; with ``--validation``, the
  validation return on the training cities instead (the only place K may be chosen).
* ``event``: the share of the idle fleet each policy asks for in the Brooklyn event's surge
  regions and halved hotspots, inside the event window and outside, and the requests left
  unserved at the surge: does the memory notice the shock?

    python benchmarks/meta_diagnostics.py gap [--policy policies/meta_rl_all_cities.pt]
    python benchmarks/meta_diagnostics.py k --ks 0,1,3,10 [--validation]
    python benchmarks/meta_diagnostics.py event
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from marl_amod.algos import meta
from marl_amod.algos import meta_imitation as mi
from marl_amod.baselines.mpc import MPCForecast, MPCOracle
from marl_amod.batch_system import BatchFleetSystem
from marl_amod.scenario import load_city
from marl_amod.system import FleetSystem
from marl_amod.transfer import STUDIES, run_strategy

VAL_CITIES = ("porto", "nyc_man_north", "shenzhen_north", "washington_dc")


def gap(policy: str, demos: str, episodes: int = 8) -> None:
    model, card = meta.load_meta(policy)
    lookahead = card["lookahead"]
    structure, place = meta.features_read(model, lookahead)
    trials = np.arange(episodes).reshape(-1, 4).T  # (K = 4, B) as the trials of training
    for name in VAL_CITIES:
        city, graph = load_city(name), meta.city_graph(load_city(name))
        own = mi.collect_city(city, episodes, 99, lookahead, learner=model, trial_episodes=4,
                              seed_of=lambda s, e: np.random.SeedSequence([s, e, 777]))  # fmt: skip
        if structure:
            own["x"] = meta.with_structure(own["x"], city, lookahead, place)
        mine = mi.CityDemos(*(torch.from_numpy(own[k]) for k in ("x", "share", "region_reward", "reward", "action")))
        stored = mi.load_demos(demos, city, lookahead, structure, place)
        theirs = mi.CityDemos(*(v[-episodes:] for v in vars(stored).values()))
        row = []
        for d in (theirs, mine):
            with torch.no_grad():
                ce = mi.imitation_losses(model, d, trials, graph, 0.97)[0].item()
            row.append(ce + float((d.share * torch.log(d.share.clamp_min(1e-12))).sum(-1).mean()))
        print(f"{name:22s} cross-entropy above the labels' entropy: MPC-F's states {row[0]:.3f}, its own {row[1]:.3f}", flush=True)


def k_sweep(policy: str, ks: list[int]) -> None:
    for study, names in STUDIES.items():
        ref = json.load(open(f"docs/meta/{study}.json"))["targets"]
        for name in names:
            oracle = ref[name]["mpc-oracle"]["metrics"]["profit"]["mean"]
            gaps = [100 * (1 - run_strategy("meta-rl", name, meta_policy=policy, adapt_episodes=k)["metrics"]["profit"]["mean"] / oracle) for k in ks]
            print(f"{name:24s} " + " ".join(f"K{k}: {g:5.1f}%" for k, g in zip(ks, gaps, strict=True)), flush=True)


def k_validation(policy: str, ks: list[int]) -> None:
    model, card = meta.load_meta(policy)
    a = card["args"]
    torch.manual_seed(0)
    for k in ks:
        scores = []
        with torch.no_grad():
            for name in a["val_cities"]:
                city, b = load_city(name), a["eval_episodes"]
                agent, system = meta.MetaAgent(model, city, card["lookahead"], b), BatchFleetSystem(city, b)
                if k:
                    meta.run_trials(agent, system, [[meta.adapt_seed(a["eval_seed"], e, j) for j in range(b)] for e in range(k)])
                last = meta.run_trials(agent, system, [[np.random.SeedSequence([a["eval_seed"], j]) for j in range(b)]], sample=False)
                scores.append(float(last.profits.mean()) / (city.horizon * agent.scale.reward))
        print(f"K={k}: validation {np.mean(scores):.4f}", flush=True)


def event(policy: str, surge: tuple[int, ...] = (8, 10), hotspots: tuple[int, ...] = (5, 6), window: range = range(6, 14)) -> None:
    for name in ("nyc_brooklyn", "nyc_brooklyn_event"):
        city = load_city(name)
        makers = {"meta K=3": lambda c=city: meta.load_policy(policy, c, 3), "meta K=0": lambda c=city: meta.load_policy(policy, c, 0),
                  "mpc-forecast": MPCForecast, "mpc-oracle": MPCOracle}  # fmt: skip
        for label, make in makers.items():
            pol, inside, outside, unserved = make(), [], [], []
            for k in range(10):
                system = FleetSystem(city)
                system.reset(np.random.SeedSequence([0, k]))
                pol.reset(system, np.random.default_rng(k))
                while not system.done:
                    t = system.sim.t
                    want = np.asarray(pol.target(system), dtype=np.float64)
                    want = np.where(want < 0, system.sim.idle, want)
                    share = want / max(want.sum(), 1.0)
                    (inside if t in window else outside).append([share[list(surge)].sum(), share[list(hotspots)].sum()])
                    system.step(want.astype(np.int64))
                    if t in window:
                        unserved.append(system.sim.requests().sum(-1)[list(surge)].sum())
            i, o = np.mean(inside, 0), np.mean(outside, 0)
            print(f"{name:20s} {label:12s} surge share in/out {i[0]:.3f}/{o[0]:.3f}  hotspots in/out {i[1]:.2f}/{o[1]:.2f}  "
                  f"unserved at the surge {np.mean(unserved):5.1f}", flush=True)  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=["gap", "k", "event"])
    parser.add_argument("--policy", default="policies/meta_rl_all_cities.pt")
    parser.add_argument("--demos", default="runs/meta_demos")
    parser.add_argument("--ks", default="0,1,2,3,4,5,6,8,10")
    parser.add_argument("--validation", action="store_true", help="k: the training cities' validation return instead")
    args = parser.parse_args()
    ks = [int(k) for k in args.ks.split(",")]
    if args.what == "gap":
        gap(args.policy, args.demos)
    elif args.what == "k":
        (k_validation if args.validation else k_sweep)(args.policy, ks)
    else:
        event(args.policy)


if __name__ == "__main__":
    main()
