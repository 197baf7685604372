"""Transfer to a new city: six strategies, and the two tables of docs/meta (issue 16).

Strategies (what each may use of the target city before it is evaluated):

* ``zero-shot``: a single-city GNN policy trained elsewhere, applied unchanged (0 episodes);
* ``fine-tune``: that policy given ``K_FINE_TUNE`` online A2C episodes in the target
  (:func:`marl_amod.algos.a2c.train` with ``init_actor``: a fresh critic, gradient steps on the
  actor, the better of start and end on a few validation episodes kept);
* ``meta-rl``: the recurrent meta-policy (:mod:`marl_amod.algos.meta`), trained on ten other cities,
  runs ``K`` adaptation episodes in the target with its memory carried, no gradient step;
* ``single-city``: a policy trained in the target city itself (the RL reference);
* ``mpc-forecast`` / ``mpc-oracle``: receding-horizon MPC on the expected demand / on the draw.

Every strategy is then evaluated on the report streams ``(seed, k)``, k < episodes, exactly as
``marl-amod evaluate --seed 0``; adaptation and fine-tuning episodes draw from their own streams
(:func:`marl_amod.algos.meta.adapt_seed`), never those. Tables add the normalised score
100 (P - P_ED) / (P_oracle - P_ED) beside the profit (equal distribution = 0, MPC-Oracle = 100).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from marl_amod.errors import ConfigError
from marl_amod.evaluation import evaluate
from marl_amod.metrics import normalised_score, score_anchors, score_points
from marl_amod.scenario import load_city

Strategy = Literal["zero-shot", "fine-tune", "meta-rl", "single-city", "mpc-forecast", "mpc-oracle"]
STRATEGIES: tuple[Strategy, ...] = ("zero-shot", "fine-tune", "meta-rl", "single-city", "mpc-forecast", "mpc-oracle")
K_FINE_TUNE = 10  # online (training) episodes fine-tuning gets in the target city
FINE_TUNE_VALIDATION = 2  # deterministic validation episodes of the start and of the end
META_POLICY = "policies/meta_rl_l1_whole_ensemble.yaml"  # two training seeds of configs/meta/bc_dagger_l1_whole_rep*.yaml (chosen by its rule: docs/meta/log.md)


@dataclass(frozen=True)
class Target:
    """A held-out task: its scenario and the single-city policies the strategies start from."""

    scenario: str
    zero_shot: str  # a GNN policy trained in another city
    single_city: str  # a GNN policy trained in this city (for the event: in Brooklyn without it)


TARGETS = {
    "san_francisco": Target("san_francisco", "policies/a2c_gnn_nyc_brooklyn.pt", "policies/a2c_sage_fast32_san_francisco.pt"),
    "nyc_brooklyn": Target("nyc_brooklyn", "policies/a2c_gnn_nyc_man_south.pt", "policies/a2c_sage_fast32_nyc_brooklyn.pt"),
    "shenzhen_downtown_west": Target(
        "shenzhen_downtown_west", "policies/a2c_gnn_nyc_brooklyn.pt", "policies/a2c_sage_fast32_shenzhen_downtown_west.pt"
    ),
    "nyc_brooklyn_event": Target("nyc_brooklyn_event", "policies/a2c_gnn_nyc_man_south.pt", "policies/a2c_sage_fast32_nyc_brooklyn.pt"),
}
STUDIES = {"intercity": ("san_francisco", "nyc_brooklyn", "shenzhen_downtown_west"), "event": ("nyc_brooklyn_event",)}


# --------------------------------------------------------------------------------------------
# Fine-tuning: K online A2C episodes from a single-city policy
# --------------------------------------------------------------------------------------------
def fine_tune(policy_path: str, scenario: str, episodes: int = K_FINE_TUNE, seed: int = 0, per_update: int = 2) -> Any:
    """The policy at ``policy_path`` after ``episodes`` online A2C episodes in ``scenario``.

    It is :func:`marl_amod.algos.a2c.train` with ``init_actor`` (a fresh critic, updates of
    ``per_update`` episodes on training streams), so fine-tuning is the one A2C. As every warm-started
    A2C run it keeps the better of the start and the end on ``FINE_TUNE_VALIDATION`` validation
    episodes each (seed 1000), never a report stream.
    """
    import tempfile

    from marl_amod.algos import a2c
    from marl_amod.checkpoints import ActorPolicy, architecture_args, feature_args, load_actor

    card = _card(policy_path)
    with tempfile.TemporaryDirectory(prefix="marl-amod-fine-tune-") as tmp:
        args = a2c.Args(
            scenario=scenario, **architecture_args(card), init_actor=str(policy_path), episodes=episodes, episodes_per_update=min(per_update, episodes), seed=seed,
            eval_every=episodes, eval_episodes=FINE_TUNE_VALIDATION, final_eval_episodes=1, run_dir=tmp, policy_out=f"{tmp}/fine_tuned.pt",
        )  # fmt: skip
        summary = a2c.train(args)
        city = load_city(scenario)
        actor, _ = load_actor(summary["policy"], city)
    return ActorPolicy(actor, city, name=f"fine-tune({Path(policy_path).stem})", **feature_args(card))


# --------------------------------------------------------------------------------------------
# One strategy on one target
# --------------------------------------------------------------------------------------------
def _card(path: str) -> dict[str, Any]:
    from marl_amod.checkpoints import read_card

    return read_card(path)


def meta_used(cards: list[dict[str, Any]]) -> dict[str, Any]:
    """What the meta-policies of ``cards`` (one, or an ensemble's members) trained on, summed: the
    tasks beside the cities, MPC-F demonstrations and DAgger episodes, and RL episodes (none when
    every member only imitated)."""
    from marl_amod.algos.meta import TRAIN_CITIES

    # (card key, what the table calls them, the card key of their episodes each): the tasks beside the cities
    kinds = [("hotspot_variants", "hotspot variants", "episodes_per_variant"), ("skew_variants", "skew variants", "episodes_per_skew_variant"),
             ("sink_variants", "sink variants", "episodes_per_sink_variant"), ("event_tasks", "event tasks", "episodes_per_event_task")]  # fmt: skip
    sources, demonstrations, dagger, rl = [], 0, 0, 0
    for card in cards:
        warm = card.get("warm_start") or {}
        demos = warm.get("demonstrations") or card.get("demonstrations")
        extra = {key: (demos or {}).get(key, []) for key, _, _ in kinds}
        cities = len((card.get("args") or {}).get("cities", TRAIN_CITIES))  # cards from before cities could be chosen: the default ten
        sources.append(f"{cities} training cities" + "".join(f" + {len(extra[key])} {label}" for key, label, _ in kinds if extra[key]))
        if demos:  # trained from an imitation of MPC-Forecast on the same cities
            demonstrations += demos["episodes_per_city"] * len(demos["cities"]) + sum(demos.get(each, 0) * len(extra[key]) for key, _, each in kinds)
        rounds = [d for d in (card.get("dagger"), warm.get("dagger")) if d]  # its own DAgger rounds and its start's
        if rounds and demos:  # the policy's own episodes there, labelled by MPC-F (MPC told the event on the event tasks)
            dagger += sum(d["rounds"] * d["episodes_per_city"] for d in rounds) * (len(demos["cities"]) + sum(map(len, extra.values())))
        if card["algorithm"] != "meta-bc":  # imitation only: no RL episode
            rl += card.get("episodes_trained") or 0
    source = sources[0]
    if len(cards) > 1:  # "seeds" only when the members are one recipe: alike in every argument all their cards hold but the run's own
        args = [c.get("args") or {} for c in cards]
        shared = set.intersection(*(set(a) for a in args)) - {"seed", "demos", "run_dir", "policy_out"}
        recipes = {repr(sorted((k, a[k]) for k in shared)) for a in args}
        kind = "seeds" if len(recipes) == 1 and len(set(sources)) == 1 else "members"
        source = f"{len(cards)} {kind} x ({source})" if len(set(sources)) == 1 else f"{len(cards)} {kind}: " + "; ".join(sources)
    used: dict[str, Any] = {"source_city": source, "source_episodes": rl or None}
    if demonstrations:
        used["demonstrations"] = demonstrations
    if dagger:
        used["dagger_episodes"] = dagger
    return used


def run_strategy(
    strategy: str, scenario: str, *, episodes: int = 10, seed: int = 0, policy: str | None = None,
    adapt_episodes: int | None = None, meta_policy: str = META_POLICY,
) -> dict[str, Any]:
    """Evaluate ``strategy`` on ``scenario``; the result record plus what the strategy used.

    ``policy`` overrides the strategy's starting policy (zero-shot, fine-tune, single-city) or the
    meta-policy (meta-rl);
    ``adapt_episodes`` overrides K (fine-tune, meta-rl).
    """
    if strategy not in STRATEGIES:
        raise ConfigError(f"unknown strategy {strategy!r}; known: {', '.join(STRATEGIES)}")
    if strategy in ("mpc-forecast", "mpc-oracle") and (policy is not None or adapt_episodes is not None):
        raise ConfigError(f"{strategy} plans with no trained policy and no adaptation: drop --policy and --adapt-episodes")
    if strategy in ("zero-shot", "single-city") and adapt_episodes is not None:
        raise ConfigError(f"{strategy} adapts nothing in the new city: --adapt-episodes is for fine-tune and meta-rl")
    if strategy == "fine-tune" and adapt_episodes is not None and adapt_episodes < 1:
        raise ConfigError(f"fine-tune needs at least one online episode in the new city, got --adapt-episodes {adapt_episodes} (K = 0 is zero-shot)")
    city = load_city(scenario)
    target = TARGETS.get(city.name)
    needs = {"zero-shot": "zero_shot", "fine-tune": "zero_shot", "single-city": "single_city"}
    if strategy in needs and policy is None:
        if target is None:
            raise ConfigError(f"strategy {strategy} on {city.name} needs --policy (known targets: {', '.join(TARGETS)})")
        policy = getattr(target, needs[strategy])
    used: dict[str, Any] = {"strategy": strategy, "target_episodes": 0}
    if strategy in ("mpc-forecast", "mpc-oracle"):
        pol: Any = strategy
        used["source"] = "expected demand" if strategy == "mpc-forecast" else "the episode's draw"
    elif strategy in ("zero-shot", "single-city"):
        pol = policy
        card = _card(policy)
        if strategy == "zero-shot" and card["scenario"] == city.name:
            raise ConfigError(f"{policy} was trained on {city.name} itself: that is the single-city strategy, not zero-shot")
        used.update(source=policy, source_city=card["scenario"], source_episodes=card.get("episodes_trained"))
        if strategy == "single-city" and card["scenario"] == city.name:
            used["target_episodes"] = card.get("episodes_trained")
    elif strategy == "fine-tune":
        k = K_FINE_TUNE if adapt_episodes is None else adapt_episodes
        card = _card(policy)
        pol = fine_tune(policy, scenario, k, seed)
        used.update(source=policy, source_city=card["scenario"], source_episodes=card.get("episodes_trained"), target_episodes=k,
                    validation_episodes=2 * FINE_TUNE_VALIDATION)
    else:
        from marl_amod.algos.meta import load_policy, trained_adaptation_episodes
        from marl_amod.ensemble import is_ensemble, read_members, read_spec

        meta_policy = policy or meta_policy
        members = read_members(meta_policy) if is_ensemble(meta_policy) else [meta_policy]
        cards = [_card(m) for m in members]  # the cards alone: load_policy builds the models
        k = trained_adaptation_episodes(cards[0]) if adapt_episodes is None else adapt_episodes
        pol = load_policy(meta_policy, city, k, seed)
        together = is_ensemble(meta_policy) and read_spec(meta_policy).together  # adapted as one: K in all, else K each
        used.update(meta_used(cards), source=meta_policy, target_episodes=k * (1 if together else len(members)))
    result = evaluate(pol, city, episodes, seed)
    result["transfer"] = used
    return result


# --------------------------------------------------------------------------------------------
# The tables
# --------------------------------------------------------------------------------------------
def check_study(study: str, strategies: tuple[str, ...] = ()) -> None:
    """A study and strategies of this module, else a ConfigError listing the known ones."""
    if study not in STUDIES:
        raise ConfigError(f"unknown study {study!r}; known: {', '.join(STUDIES)}")
    if unknown := sorted(set(strategies) - set(STRATEGIES)):
        raise ConfigError(f"unknown strategy {unknown[0]!r}; known: {', '.join(STRATEGIES)}")


def run_study(study: str, *, episodes: int = 10, seed: int = 0, meta_policy: str = META_POLICY, strategies: tuple[str, ...] = STRATEGIES,
              previous: dict[str, Any] | None = None, progress: Any = None) -> dict[str, Any]:  # fmt: skip
    """Every strategy (and equal distribution, the 0 of the score) on every target of ``study``.

    With ``strategies`` a subset, the other rows come from ``previous`` (an earlier payload of the
    same study, episodes and seed), so retraining one policy reruns one row, not the MPC rows.
    """
    check_study(study, strategies)
    if previous is not None and (previous.get("study"), previous.get("episodes"), previous.get("seed")) != (study, episodes, seed):
        raise ConfigError(f"the saved {previous.get('study')} table was run with {previous.get('episodes')} episodes, seed {previous.get('seed')}: "
                          "rows of other episodes are not comparable with it; rerun these rows with its episodes and seed, "
                          "or every row (no --strategy), or write elsewhere (--out)")  # fmt: skip
    out: dict[str, Any] = {"study": study, "episodes": episodes, "seed": seed, "targets": {}}
    for scenario in STUDIES[study]:
        old = (previous or {}).get("targets", {}).get(scenario, {})
        rows = {"equal-distribution": old.get("equal-distribution") or evaluate("equal-distribution", scenario, episodes, seed)}
        for strategy in STRATEGIES:
            if strategy in strategies:
                rows[strategy] = run_strategy(strategy, scenario, episodes=episodes, seed=seed, meta_policy=meta_policy)
                if progress is not None:
                    progress(scenario, strategy, rows[strategy]["metrics"]["profit"]["mean"])
            elif strategy in old:
                rows[strategy] = old[strategy]  # a row not asked for: kept from the previous run
        pair = score_anchors(mean_profits(rows))
        if pair is not None:
            for rec in rows.values():
                rec["normalised_score"] = normalised_score(rec["metrics"]["profit"]["mean"], *pair)
        out["targets"][scenario] = rows
    return out


def mean_profits(rows: dict[str, dict[str, Any]]) -> dict[str, float]:
    """A target's mean profit by strategy (and equal distribution), from its evaluation records."""
    return {name: rec["metrics"]["profit"]["mean"] for name, rec in rows.items()}


def study_scores(payload: dict[str, Any]) -> dict[str, list[tuple[str, float, float]]]:
    """Per target, every strategy's (name, normalised score, episode std in score points): what
    :func:`marl_amod.plots.score_bars` draws. Equal distribution is the figure's 0 line, not a bar;
    a target without both anchors (a partial run: ``--strategy`` on a fresh folder) has no scores."""
    groups = {}
    for scenario, rows in payload["targets"].items():
        pair = score_anchors(mean_profits(rows))
        if pair is None:
            continue
        groups[scenario] = [(name, rec["normalised_score"], score_points(rec["metrics"]["profit"]["std"], *pair))
                            for name, rec in rows.items() if name != "equal-distribution"]  # fmt: skip
    return groups


def study_markdown(payload: dict[str, Any]) -> str:
    """The study as markdown tables: profit (k$) mean ± std, normalised score, served, rebalancing
    cost, and the episodes each strategy used in the target and before."""
    lines = []
    for scenario, rows in payload["targets"].items():
        lines += [f"### {scenario}", "",
                  "| strategy | profit (k$) | score (ED 0, oracle 100) | served | reb. cost (k$) | episodes in target | trained on (episodes) |",
                  "|---|---|---|---|---|---|---|"]  # fmt: skip
        for name, rec in rows.items():
            m = rec["metrics"]
            used = rec.get("transfer", {})
            source = used.get("source_city", "-")
            if used.get("source_episodes") is not None:
                source = f"{source} ({used['source_episodes']:,})"
            if used.get("demonstrations"):
                source += f" + {used['demonstrations']:,} MPC-F demos"
            if used.get("dagger_episodes"):
                source += f" + {used['dagger_episodes']:,} DAgger"
            score = f"{rec['normalised_score']:.1f}" if "normalised_score" in rec else "-"  # no MPC-Oracle row to scale by
            in_target = f"{used.get('target_episodes', 0) or 0:,}"
            if used.get("validation_episodes"):
                in_target += f" + {used['validation_episodes']} val."
            lines.append(
                f"| {name} | {m['profit']['mean'] / 1e3:.1f} ± {m['profit']['std'] / 1e3:.1f} | {score} "
                f"| {m['served_demand']['mean']:,.0f} | {m['rebalancing_cost']['mean'] / 1e3:.2f} | {in_target} | {source} |"
            )
        lines.append("")
    return "\n".join(lines)
