"""What the offline algorithms (BC, IQL, CQL) share: the dataset as tensors, minibatches, the
policy's log-likelihood of a logged action in both modes, and the update loop.

The algorithm files (:mod:`.bc`, :mod:`.iql`, :mod:`.cql`) hold their networks and losses and
read top to bottom; the imitation term they share (:func:`imitation_loss`) is here; :func:`fit` runs any of them: ``updates`` gradient steps on minibatches of the
dataset, a validation every ``eval_every`` updates (deterministic actor on the validation seeds,
never the report seeds; logged, and the kept actor when ``keep: best``; by default the last actor
is shipped, so nothing but the dataset shapes it), the resumable state, Ctrl-C, and the policy
card (with the dataset's card: behaviour score and normalised scores).

Modes. Centralised: alpha = actor(x) on the global graph, pi(y|s) = Dir(y; alpha). Decentralised:
every agent computes alpha_i from its own local observation (the dataset's ``observations``, cut
by :func:`~marl_amod.env.observations.split_local`) and draws g_i ~ Gamma(alpha_i, 1); the env
normalises, so the logged joint action y = g / sum(g) has density Dir(y; alpha) (the Gamma
weights' scale is not observed, the normalised action is). Critics always read the global graph
(centralised training, decentralised execution).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np
import torch
from pydantic import Field, model_validator

from marl_amod.algos import common as C
from marl_amod.datasets import OfflineDataset, normalised_score, read_card
from marl_amod.env.features import FEATURE_SCALE
from marl_amod.env.observations import split_local
from marl_amod.errors import ConfigError, DataError
from marl_amod.models.dense import DenseGraph
from marl_amod.models.gnn import Graph
from marl_amod.scenario import City
from marl_amod.selection import Selection

Imitation = Literal["ce", "l1"]


class OfflineArgs(C.RunArgs):
    """What every offline run has; ``episodes`` is replaced by ``updates`` (no env episodes)."""

    dataset: str
    """the offline dataset (.npz, format 2; its card beside it) — `marl-amod datasets` makes them"""
    updates: int = Field(5000, ge=1)
    """gradient steps"""
    batch_size: int = Field(256, ge=1)
    """transitions per gradient step"""
    lr_actor: float = Field(1e-3, gt=0)
    """Adam learning rate of the actor"""
    eval_every: int = Field(500, ge=1)
    """updates between validation evaluations (validation seeds; the best actor is kept)"""
    reward_scale: float = Field(0.001, gt=0)
    """multiplies the logged money rewards (a step earns a few thousand in Brooklyn)"""
    lr_decay: bool = False
    """decay every learning rate linearly to zero over the updates: the shipped (last) actor is then
    a settled one, not a random point of a noisy descent (DTV's targets react to requests the
    actor cannot see, and its validation profit swung by 8k between checkpoints without it)"""
    imitation: Imitation = "ce"
    """the imitation loss of the logged action (BC's, IQL's advantage-weighted one, CQL's cloning
    phase; :func:`imitation_loss`): ce, the cross-entropy of the logged shares under the policy's
    mean; l1, the absolute error of the mean's shares, i.e. the vehicles a step off as a share of
    the fleet, every vehicle alike in every region (the cross-entropy weighs a share error at region i
    by about 1 / y_i, least at the busiest regions)"""
    shortfall_weight: float = Field(0.0, ge=0, allow_inf_nan=False)
    """``imitation: l1`` only: a vehicle short of the logged target at a region that receives vehicles
    (logged target above its idle count) costs 1 + this, a vehicle over costs 1: short there, requests
    go unserved; over, a vehicle was moved that need not have been"""
    surplus_price: bool = False
    """with ``shortfall_weight`` only: a vehicle over at a receiving region costs 1 + shortfall_weight x
    move / trip instead of 1, where trip is what a served request earns and move what a rebalancing
    move costs, both read from the city and the dataset (:func:`receiver_prices`; on the card): the
    shortfall prices the request a missing vehicle leaves unserved, this the paid move an extra
    vehicle made (docs/offline "BC fidelity" 12)"""
    keep: Literal["last", "best"] = "last"
    """the actor shipped: the last one (no env interaction at all: offline RL proper) or the best
    on the validation seeds (uses ``eval_episodes`` env episodes per validation, as online runs do:
    online policy selection, as D4RL papers report it; with ``init_actor`` the start is a candidate
    too, so an improvement step is kept only where the validation seeds confirm it)"""

    @model_validator(mode="after")
    def _shortfall_prices_l1(self) -> OfflineArgs:
        if self.shortfall_weight and self.imitation != "l1":
            raise ValueError(f"shortfall_weight weighs the vehicles of imitation: l1; imitation is {self.imitation} "
                             "(set imitation: l1, or shortfall_weight: 0)")  # fmt: skip
        if self.surplus_price and not self.shortfall_weight:
            raise ValueError("surplus_price prices a receiving region's surplus against its shortfall: set shortfall_weight > 0 "
                             "(with imitation: l1), or surplus_price: false")  # fmt: skip
        return self

    def ignored_keys(self) -> dict[str, str]:
        return {**super().ignored_keys(), "episodes": "offline runs take no env episodes; set updates",
                "num_envs": "offline runs step no env in lockstep (they learn from the dataset; validation plays one episode at a time)"}  # fmt: skip


class CriticArgs(OfflineArgs):
    """What the offline learners with a Q critic (IQL, CQL) add: the critic ships in the policy
    file, and the policy may play by it."""

    selection: Selection | None = None
    """Q-guided action selection (:mod:`marl_amod.selection`): the policy plays the best of the
    actor's mean and ``candidates`` draws around it by the shipped critic (the final evaluation
    too; validation stays on the mean). None: the Dirichlet mean, as every shipped policy"""


def setup(args: OfflineArgs) -> tuple[City, Data, bool, DenseGraph, torch.Generator]:
    """What every offline run starts with: threads and seeds set, then (city, its dataset, whether the
    run is decentralised, the graph, the minibatch generator).

    The graph is the dense small-graph form (:mod:`marl_amod.models.dense`): a minibatch is B
    copies of one city graph, one matmul per layer instead of torch-geometric's scatter over
    B * N nodes; the parameters are the same, so the shipped actor runs on either path."""
    from marl_amod.scenario import load_city

    torch.set_num_threads(args.threads)
    C.seed_everything(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    city = load_city(args.scenario)
    edge_index = torch.tensor(np.array(city.edge_index), dtype=torch.long)
    return city, Data(args, city), args.mode == "decentralised", DenseGraph(edge_index, city.n_regions), gen


class Batch(dict):
    """A minibatch: x, next_x (B, N, F); action (B, N); reward, done (B,); decentralised runs also
    own, nbrs, mask and their next_ versions (B, N, F), (B, N, K, F), (B, N, K)."""


def check_fits(data: OfflineDataset, path: str | Path, city: City, lookahead: int | None = None, arrivals_now: bool | None = None,
               reader: str = "config") -> None:  # fmt: skip
    """Refuse, before any work, a dataset that cannot serve: empty, of another city, or with other
    features than the reader's (``None``: not checked). ``reader`` names what the user would change:
    ``"config"`` (a training run's keys) or ``"policy"`` (a trained policy reads fixed features:
    collect the data again)."""
    meta = data.meta
    if len(data) == 0:
        raise DataError(f"{path} holds no transitions")
    if meta["scenario"] != city.name or meta["n_agents"] != city.n_regions:
        raise DataError(f"{path} was collected on {meta['scenario']} ({meta['n_agents']} regions), this run is on {city.name} ({city.n_regions})")
    for key, ours, flag in (("lookahead", lookahead, "--lookahead {}"), ("arrivals_now", arrivals_now, "--arrivals-now")):
        theirs = meta.get(key) if key == "lookahead" else bool(meta.get(key))  # older datasets lack arrivals_now: off
        if ours is None or theirs == ours:
            continue
        value = str(theirs).lower() if isinstance(theirs, bool) else theirs
        fix = (f"set {key}: {value} in the config" if reader == "config"
               else f"the policy reads {key} {ours}: collect the data with {flag.format(ours)}" if ours is not False
               else f"the policy reads {key} false: collect the data without {flag}")  # fmt: skip
        raise ConfigError(f"{path} has {key} {value}; {fix}")


class Data:
    """The dataset as float tensors (the global view, plus the local one for decentralised runs)."""

    def __init__(self, args: OfflineArgs, city: City, loaded: OfflineDataset | None = None, reader: str = "config") -> None:
        """``loaded``: ``args.dataset`` already read (its caller's copy, not read again); ``reader``: as :func:`check_fits`."""
        path = Path(args.dataset)
        data = loaded if loaded is not None else OfflineDataset.load(path)
        self.card = read_card(path) if path.with_suffix(".json").is_file() else {}
        check_fits(data, path, city, args.lookahead, args.arrivals_now, reader)
        view = data.global_view()
        t = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731 - a copy: npz arrays are read-only
        self.tensors: dict[str, torch.Tensor] = {
            "x": t(view["x"]), "next_x": t(view["next_x"]), "ctx": t(view["ctx"]), "next_ctx": t(view["next_ctx"]), "action": t(view["action"]),
            "reward": t(view["reward"]) * args.reward_scale, "done": t(view["done"]),
        }  # fmt: skip
        if args.mode == "decentralised":
            f = data.n_features
            for prefix, obs in (("", data.observations), ("next_", data.next_observations)):
                own, _ctx, nbrs, mask = split_local(t(obs), f)
                self.tensors.update({f"{prefix}own": own, f"{prefix}nbrs": nbrs, f"{prefix}mask": mask})
        self.size = len(data)
        self.meta = data.meta
        self.prices = receiver_prices(city, self.tensors["x"], t(data.actions)) if args.surplus_price else None
        # the weight of a receiving region's surplus vehicle beyond 1 (imitation_loss's surplus)
        self.surplus = args.shortfall_weight * self.prices["move"] / self.prices["trip"] if self.prices else 0.0

    def sample(self, batch: int, gen: torch.Generator) -> Batch:
        idx = torch.randint(0, self.size, (batch,), generator=gen)
        return Batch({k: v[idx] for k, v in self.tensors.items()})


def receiver_prices(city: City, x: torch.Tensor, action: torch.Tensor, scale: float = FEATURE_SCALE) -> dict[str, float]:
    """The two prices of ``surplus_price``, in money: ``trip``, what a served request earns (the city's
    fare minus operating cost, :attr:`City.margin`, averaged over an episode's expected requests), and
    ``move``, what the behaviour policy paid per vehicle it moved: the env's own rebalancing of the
    logged steps (its floor of the logged weights ``action`` (T, N) over the idle vehicles read from
    the node features ``x`` (T, N, F), then the coordinator's min-cost flows, on the reduced network
    where the city's travel times are metric as in the env), its cost over the vehicles it moves."""
    from marl_amod.coordinator.coordinator import Coordinator
    from marl_amod.coordinator.rebalance import floor_targets

    rate = city.demand_rate[: city.horizon]
    if rate.sum() <= 0:
        raise DataError(f"city {city.name!r} expects no request in an episode: no trip price to weigh a surplus against")
    trip = float((rate * city.margin[: city.horizon]).sum() / rate.sum())
    idle = np.rint(x[..., 0].double().numpy() / scale).astype(np.int64)  # (T, N) vehicles
    target = floor_targets(action.double().numpy(), idle.sum(-1))  # the env's targets (-1: stay)
    flows = Coordinator(city).rebalance(idle, target)  # the env's solver, network and tie-breaking
    if flows.sum() == 0:
        raise DataError("the logged actions move no vehicle: no rebalancing price to weigh a surplus with (surplus_price)")
    return {"trip": trip, "move": float((flows * city.reb_cost).sum() / flows.sum())}


def concentrations(
    actor: torch.nn.Module, b: Batch, edge_index: Graph, local: bool, prefix: str = "", time: bool = False
) -> torch.Tensor:
    """alpha (B, N): from the global graph (centralised; with the time context on every node when
    ``time``, as ``actor_time`` runs) or from each agent's own observation."""
    if local:
        return actor.forward_local(b[f"{prefix}own"], b[f"{prefix}nbrs"], b[f"{prefix}mask"])
    return actor(C.with_time(b[f"{prefix}x"], b.get(f"{prefix}ctx"), time), edge_index)


def imitation_loss(
    actor: torch.nn.Module, b: Batch, graph: Graph, local: bool, time: bool = False, kind: Imitation = "ce",
    shortfall: float = 0.0, surplus: float = 0.0,
) -> torch.Tensor:
    """Per-transition loss (B,) of imitating the logged action y (normalised) with the policy's
    Dirichlet mean m = alpha / sum(alpha), which is what the deterministic policy plays.

    ``ce``: the cross-entropy -sum_i y_i log m_i. Why not the likelihood log Dir(y; alpha): maximum
    likelihood fits the Dirichlet's geometric mean (E log y), and the logged targets of INF, DTV and
    MPC are mostly zeros (78% of INF's), whose clamped logs dominate it, so the arithmetic mean the
    deterministic policy plays lands far from the behaviour (on INF 27 vehicles a step off against 15
    with this loss). The cross-entropy is minimised by the conditional mean of y: a proper score for
    what is played. It leaves the total concentration (how widely sampled actions spread) free;
    fitting that by the likelihood as well moves every alpha_i by the same amount (d sum / d alpha_i
    = 1), which drags the mean towards uniform (INF: 45k instead of 55k on the validation seeds).

    ``l1``: sum_i |m_i - y_i|, twice the vehicles a step off over the fleet M. Near its optimum the
    cross-entropy is sum_i (m_i - y_i)^2 / (2 y_i): a vehicle off at a region holding a third of the
    fleet costs some 30 times less than at one holding 1%, so a clone that cannot fit every region
    may spend its error at the busiest ones, where MPC sends its vehicles. The absolute error prices
    every vehicle alike (and is minimised by the median, not the mean, where the logged targets are
    tied). What each did on MPC-Forecast: docs/offline "BC fidelity" 11.
    ``shortfall`` prices a vehicle short at a receiving region (:func:`receivers`) 1 + ``shortfall``
    times one over: the quantile loss of the receivers' targets, where a vehicle short leaves
    requests unserved; ``surplus`` prices a vehicle over there 1 + ``surplus`` times
    (``surplus_price``: a move that was paid for).
    """
    alpha = concentrations(actor, b, graph, local, time=time)  # (B, N)
    mean = alpha / alpha.sum(-1, keepdim=True)
    y = b["action"] / b["action"].sum(-1, keepdim=True).clamp_min(1e-12)
    receives = receivers(b["x"], y)[1] if kind == "l1" and (shortfall or surplus) else None
    return shares_loss(mean, y, kind, receives, shortfall, surplus)


def shares_loss(
    mean: torch.Tensor, y: torch.Tensor, kind: Imitation = "ce", receives: torch.Tensor | None = None,
    shortfall: float = 0.0, surplus: float = 0.0,
) -> torch.Tensor:
    """Per-decision loss (...,) of playing the shares ``mean`` (..., N) where the label is ``y``: the
    two kinds of :func:`imitation_loss`, whose docstring says why each. ``receives`` (..., N) marks
    the receiving regions whose vehicles short (over) ``l1`` prices 1 + ``shortfall`` (``surplus``)
    times; the meta-policy's imitation (:mod:`marl_amod.algos.meta_imitation`) reads it too."""
    if kind == "ce":
        return -(y * torch.log(mean.clamp_min(1e-8))).sum(-1)
    if kind == "l1":
        short, over = (y - mean).clamp_min(0), (mean - y).clamp_min(0)
        if receives is not None:
            short, over = short * (1 + shortfall * receives), over * (1 + surplus * receives)
        return (short + over).sum(-1)
    raise ConfigError(f"unknown imitation loss {kind!r}; known: ce, l1")


def receivers(x: torch.Tensor, y: torch.Tensor, scale: float = FEATURE_SCALE) -> tuple[torch.Tensor, torch.Tensor]:
    """(idle vehicles, receives) per region (..., N): the idle counts read from the node features
    (column 0 times ``scale``) and whether the logged target shares ``y`` ask a region for more
    than it holds (y M above its idle count): the regions a planner moves vehicles into, where a
    vehicle short leaves requests unserved."""
    idle = torch.round(x[..., 0] / scale)
    return idle, y * idle.sum(-1, keepdim=True) > idle + 0.5


def sink_margin_targets(x: torch.Tensor, action: torch.Tensor, margin: float, scale: float = FEATURE_SCALE) -> torch.Tensor:
    """Logged target shares (T, N) with ``margin`` vehicles added to every region that receives
    vehicles (target above its idle count), taken from the other regions' targets in proportion.

    Why: the env plays floor(w_i M) and the coordinator only moves vehicles into regions below
    their target, so a share a little low at a receiving region loses a vehicle there while a low
    share elsewhere costs nothing (that region keeps its vehicles unless a receiver needs them).
    The logged targets of a planner (MPC, DTV, INF) sum to M exactly, so their clone has no margin
    at all; this one centres the receivers' targets inside the floor's bin. The idle counts and
    M are read from the node features (idle times ``scale``); steps with no idle vehicle keep the
    logged share.
    """
    y = action / action.sum(-1, keepdim=True).clamp_min(1e-12)
    idle, sink = receivers(x, y, scale)  # (T, N) each
    m = idle.sum(-1, keepdim=True)
    target = y * m  # the logged targets in vehicles
    others = torch.where(sink, torch.zeros_like(target), target)
    extra = torch.minimum(margin * sink.sum(-1, keepdim=True), others.sum(-1, keepdim=True))
    moved = target + margin * sink - extra * others / others.sum(-1, keepdim=True).clamp_min(1e-12)
    moved = moved - (moved.sum(-1, keepdim=True) - m) * sink / sink.sum(-1, keepdim=True).clamp_min(1)  # where others ran short
    return torch.where(m > 0, moved / m.clamp_min(1), y)


class Update(Protocol):
    def __call__(self, b: Batch, step: int) -> dict[str, float]:
        """One gradient step on minibatch ``b``; returns the losses to log."""


def fit(
    args: OfflineArgs, algorithm: str, city: City, data: Data, actor: torch.nn.Module, update: Update,
    parts: dict[str, Any], gen: torch.Generator, *, resume: str | None, progress: C.Progress | None, config_path: str | None,
    critic: tuple[torch.nn.Module, int, str] | None = None,
) -> dict[str, Any]:
    """Run ``update`` for ``args.updates`` steps with validation, resume and the card; ``parts``
    are the networks and optimisers whose state a resumed run restores (by name); ``critic``
    (a TwinQ, its hidden units and conv) ships in the policy file with ``args.selection``."""
    if not resume:
        if args.standardise_inputs:  # the dataset's statistics (of what the actor reads); a warm start brings its own
            actor.fit_inputs(C.with_time(data.tensors["x"], data.tensors["ctx"], args.actor_time))
        C.warm_start(actor, args, city)
    step, prior_wall, best = 0, 0.0, C.BestActor.of(actor)
    if args.init_actor and args.keep == "best" and not resume:  # a conservative improvement step: the start
        best.validate(actor, city, args)  # is a candidate, so the shipped actor never validates below it
    if resume:
        st = C.load_state(resume, algorithm, args)
        C.restore(resume, st, **parts)
        step, prior_wall, best = st["episode"], st["wall_s"], C.BestActor(st["best_val"], st["best_actor"])
        gen.set_state(st["gen"])
    log = C.Logger(args.run_dir, resume_from=step if resume else None)
    timer = C.Timer(prior_wall)

    def save() -> tuple[Path, int]:
        path = C.state_path(args)
        C.save_state(path, args, algorithm=algorithm, **{k: p.state_dict() for k, p in parts.items()}, gen=gen.get_state(),
                     episode=step, best_val=best.value, best_actor=best.state, wall_s=timer())  # fmt: skip
        return path, step

    optimisers = [p for p in parts.values() if isinstance(p, torch.optim.Optimizer)]
    with C.interruptible(save):
        while step < args.updates:
            if args.lr_decay:
                for group in (g for opt in optimisers for g in opt.param_groups):
                    group["lr"] = group.setdefault("initial_lr", group["lr"]) * (1 - step / args.updates)
            stats = update(data.sample(args.batch_size, gen), step)
            step += 1
            out_of_time = bool(args.time_limit_s) and timer() > args.time_limit_s  # checked every update, as A2C and SAC do
            if step % args.eval_every == 0 or step >= args.updates or out_of_time:
                stats["eval/profit"] = best.validate(actor, city, args)  # the update that ran out of time competes too
                stats["time/wall_s"] = timer()
                log.log(step, **stats)
                save()
                if progress is not None:
                    progress(step, args.updates, stats)
                if out_of_time:
                    break
            C.stop_if_asked()  # a Ctrl-C during the update stops the run after it
    log.close()
    if args.keep == "best":
        actor.load_state_dict(best.state)
    extra = {**_dataset_fields(data, step), "kept": args.keep, "best_validation": best.value}
    if data.prices:
        extra["receiver_prices"] = {**data.prices, "surplus_weight": data.surplus}
    spec = None
    if critic is not None:
        net, hidden, conv = critic
        spec = C.CriticSpec(net, {"n_features": C.run_features(args), "hidden": hidden, "conv": conv}, getattr(args, "selection", None))
    return C.finish_run(args, algorithm, actor, city, timer(), 0, config_path, extra=extra, critic=spec)


def _dataset_fields(data: Data, step: int) -> dict[str, Any]:
    """What the policy card says about the data it learned from (and the normalised-score references)."""
    fields: dict[str, Any] = {"updates": step, "dataset": {k: data.meta[k] for k in ("policy", "seed", "episodes", "transitions")}}
    refs = data.card.get("reference_scores")
    if refs:  # a mixture's card scores each behaviour apart (datasets.mix_cards)
        key = "behaviour_score" if "behaviour_score" in data.card else "behaviour_scores"
        fields["dataset"].update({key: data.card[key], "reference_scores": refs})
    return fields


def card_normalised(card: dict[str, Any]) -> float | None:
    """A policy card's normalised score (0 = ED, 100 = MPC-Oracle) from its dataset's references."""
    refs = card.get("dataset", {}).get("reference_scores")
    return None if not refs or card.get("profit_mean") is None else normalised_score(card["profit_mean"], refs)
