"""Meta-RL through recurrence (RL², the paper's "Meta-RL"): cities as tasks, one recurrent policy.

Read top to bottom: the task set and its per-city scaling, the agent that carries memory, a
trial, Args, ``train``, then adaptation to a new city (no gradient steps).

Tasks. The ten training cities are every real city except the three held out for the
inter-city study (San Francisco, NY Brooklyn, Shenzhen downtown west). Fleets differ 35-fold
(Rome 78 vehicles, Chicago 2,716), so one shared policy needs inputs and rewards in per-city
units (:class:`CityScale`):

* vehicle counts (idle, supply) are divided by the fleet per region, fleet / N;
* request values (expected fares out of a region) are divided by the mean fare and by fleet / N,
  so they read as expected requests in the same unit as the vehicles, and the supply-demand
  balance of a city stays visible;
* a last column is the step fraction t / horizon;
* the reward is the step's profit divided by the city's expected fare revenue per step
  (``forecast_rate * price`` over the episode, / horizon): about 0.5-1 per step in every city.

Trials. A trial is ``trial_episodes`` consecutive episodes on one city, drawn at random, with the
recurrent memory (:class:`~marl_amod.models.recurrent.RecurrentGNN`) carried from one episode to
the next; the previous action and reward are reset to zero at each episode start. The A2C update
treats the trial as one sequence (discount ``gamma``, GAE ``gae_lambda``; back-propagation through
the whole trial), so the memory learns to infer the city from what happened in earlier episodes.

Warm start (optional, ``bc_trials`` > 0). Before the RL² updates, the model imitates MPC-Forecast
(the expected-demand planner, never the oracle) on trials of the training cities: Dirichlet
log-likelihood of MPC's desired distribution plus the critic fitted to the trials' returns. A2C
from scratch learns slowly on a shared 2-core machine; the warm start gives it a competent
starting point, and the RL² updates then train the memory to adapt. Training cities only.

Adaptation. In a new city the policy runs ``trial_episodes - 1`` episodes (stochastic actions,
their own demand streams, never the report streams), and each evaluation episode starts from
the memory those left: a handful of episodes and no gradient step.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field

from marl_amod.algos import common as C
from marl_amod.algos.rollout import train_seed
from marl_amod.baselines.base import WeightPolicy
from marl_amod.env.features import node_features
from marl_amod.models.distributions import dirichlet
from marl_amod.models.recurrent import RecurrentGNN
from marl_amod.scenario import City, load_city
from marl_amod.system import FleetSystem

TRAIN_CITIES = (
    "chicago", "nyc_man_middle", "nyc_man_north", "nyc_man_south", "porto", "rome",
    "shenzhen_baoan", "shenzhen_downtown_east", "shenzhen_north", "washington_dc",
)  # fmt: skip
HELD_OUT = ("san_francisco", "nyc_brooklyn", "shenzhen_downtown_west")


# --------------------------------------------------------------------------------------------
# Cities as tasks: per-city units
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CityScale:
    """The units that make cities of any fleet and demand size look alike to one policy."""

    vehicles: float  # fleet / N: vehicles per region
    requests: float  # mean fare * fleet / N: a region's request value in "vehicles per region"
    reward: float  # expected fare revenue per control step (forecast demand x fares)

    @classmethod
    def of(cls, city: City) -> CityScale:
        steps = slice(0, city.horizon)
        rate, price = city.forecast_rate[steps], city.price[steps]
        revenue, requests = float((rate * price).sum()), float(rate.sum())
        per_region = city.fleet_size / city.n_regions
        return cls(vehicles=per_region, requests=revenue / max(requests, 1e-9) * per_region, reward=revenue / city.horizon)


def task_features(system: FleetSystem, scale: CityScale, lookahead: int) -> np.ndarray:
    """(N, 2T + 2) float32: the paper's features in per-city units, then t / horizon."""
    raw = node_features(system, lookahead, scale=1.0).astype(np.float64)  # idle, supply x T, value x T
    raw[:, : 1 + lookahead] /= scale.vehicles
    raw[:, 1 + lookahead :] /= scale.requests
    step = np.full((raw.shape[0], 1), system.t / system.city.horizon)
    return np.concatenate([raw, step], axis=1).astype(np.float32)


def n_task_features(lookahead: int) -> int:
    return 2 + 2 * lookahead


# --------------------------------------------------------------------------------------------
# The agent: a policy with memory on one city
# --------------------------------------------------------------------------------------------
class MetaAgent:
    """The recurrent policy on one city: its scale, graph, memory and previous action/reward."""

    def __init__(self, model: RecurrentGNN, city: City, lookahead: int) -> None:
        self.model, self.city, self.lookahead = model, city, lookahead
        self.scale = CityScale.of(city)
        self.edge_index = torch.as_tensor(np.array(city.edge_index), dtype=torch.long)
        self.memory = model.initial_memory(city.n_regions)  # a new trial: nothing known yet
        self.new_episode()

    def new_episode(self) -> None:
        """Previous action and reward restart; the memory does not (that is the adaptation)."""
        n = self.city.n_regions
        self.prev_action, self.prev_reward = torch.zeros(n), torch.zeros(())

    def act(self, system: FleetSystem, sample: bool) -> tuple[np.ndarray, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(weights (N,), log pi (), entropy (), value ()) and the memory moves one step."""
        x = torch.as_tensor(task_features(system, self.scale, self.lookahead))
        alpha, v, self.memory = self.model(x, self.prev_action, self.prev_reward, self.memory, self.edge_index)
        dist = dirichlet(alpha)
        if sample:
            y = dist.sample().clamp_min(1e-6)
            y = y / y.sum()
        else:
            y = alpha / alpha.sum()  # the Dirichlet mean, as every deterministic evaluation
        self.prev_action = y.detach() * self.city.n_regions  # mean 1 per region in every city
        return y.detach().numpy().astype(np.float64), dist.log_prob(y.detach()), dist.entropy(), v

    def observe(self, reward: float) -> float:
        """Feed the step's profit back (in per-city units); returns the scaled reward."""
        r = reward / self.scale.reward
        self.prev_reward = torch.tensor(r, dtype=torch.float32)
        return r


@dataclass
class Trial:
    """What a trial produced, one entry per control step (across its episodes), plus per-episode profit."""

    logps: list[torch.Tensor]
    entropies: list[torch.Tensor]
    values: list[torch.Tensor]
    rewards: list[float]  # scaled
    profits: list[float]  # money, one per episode


def run_trial(agent: MetaAgent, system: FleetSystem, seeds: list[np.random.SeedSequence], sample: bool = True) -> Trial:
    """Run one episode per seed on ``system`` with ``agent``'s memory carried across them."""
    trial = Trial([], [], [], [], [])
    for seed in seeds:
        system.reset(seed)
        agent.new_episode()
        profit = 0.0
        while not system.done:
            w, logp, ent, v = agent.act(system, sample)
            out = system.step(system.targets_from_weights(w))
            trial.logps.append(logp), trial.entropies.append(ent), trial.values.append(v)
            trial.rewards.append(agent.observe(out.reward))
            profit += out.reward
        trial.profits.append(profit)
    return trial


def advantages(rewards: list[float], values: torch.Tensor, gamma: float, lam: float) -> tuple[torch.Tensor, torch.Tensor]:
    """GAE(lambda) over one trial (terminal at its end); returns (advantages, value targets), (S,)."""
    v = values.detach().numpy()
    adv, running = np.zeros(len(rewards), dtype=np.float32), 0.0
    for t in reversed(range(len(rewards))):
        nxt = v[t + 1] if t + 1 < len(rewards) else 0.0
        running = rewards[t] + gamma * nxt - v[t] + gamma * lam * running
        adv[t] = running
    adv_t = torch.as_tensor(adv)
    return adv_t, adv_t + values.detach()


# --------------------------------------------------------------------------------------------
# Training
# --------------------------------------------------------------------------------------------
class Args(C.RunArgs):
    scenario: str = "nyc_brooklyn"
    """not trained on: the held-out city the run's card names; training draws from ``cities``"""
    cities: list[str] = Field(default_factory=lambda: list(TRAIN_CITIES), min_length=1)
    """training cities (tasks); the held-out ones must not be among them"""
    hidden: int = Field(64, ge=1)
    """memory and hidden units of the recurrent GNN"""
    conv: Literal["gcn", "sage"] = "sage"
    """message passing between regions' memories"""
    episodes: int = Field(20000, ge=1)
    """training episodes in all (trials x trial_episodes)"""
    trial_episodes: int = Field(6, ge=2, le=11)
    """episodes per trial on one city with memory carried; adaptation uses one fewer"""
    trials_per_update: int = Field(2, ge=1)
    """trials (cities) per gradient step"""
    lr: float = Field(1e-3, gt=0)
    """Adam learning rate (actor and critic share the recurrent trunk)"""
    gae_lambda: float = Field(0.95, ge=0, le=1)
    """GAE lambda of the advantages"""
    value_coef: float = Field(0.5, ge=0)
    """weight of the critic loss"""
    entropy_coef: float = Field(0.0, ge=0)
    """weight of the policy entropy bonus"""
    max_grad_norm: float = Field(1.0, gt=0)
    """gradient clipping (recurrent nets need it tight)"""
    bc_trials: int = Field(0, ge=0)
    """warm start: MPC-Forecast trials per training city to imitate before RL² (0: none)"""
    bc_epochs: int = Field(20, ge=1)
    """passes over the demonstrations"""
    bc_lr: float = Field(3e-3, gt=0)
    """Adam learning rate of the warm start"""
    val_cities: list[str] = Field(default_factory=lambda: ["porto", "nyc_man_north", "shenzhen_north", "washington_dc"], min_length=1)
    """training cities whose adapted profit (validation seeds) picks the best model"""
    eval_every: int = Field(600, ge=1)
    """episodes between validations (and training-state saves)"""
    run_dir: str = "runs/meta"
    """logs, the resumable training state"""

    def ignored_keys(self) -> dict[str, str]:
        return {"actor": "meta-RL always uses the recurrent GNN", "mode": "meta-RL is centralised",
                "central_critic": "meta-RL is centralised"}  # fmt: skip


def _check_tasks(args: Args) -> None:
    from marl_amod.errors import ConfigError

    leaked = sorted(set(args.cities) & set(HELD_OUT)) + ([args.scenario] if args.scenario in args.cities else [])
    if leaked:
        raise ConfigError(f"meta-RL training cities include held-out {sorted(set(leaked))}; the study tests on them")


def validate(model: RecurrentGNN, args: Args, systems: dict[str, FleetSystem]) -> float:
    """Mean scaled reward of the last (deterministic) episode of a trial on each validation city."""
    scores = []
    with torch.no_grad():
        for name in args.val_cities:
            system = systems[name]
            agent = MetaAgent(model, system.city, args.lookahead)
            adapt = [adapt_seed(args.eval_seed, k) for k in range(args.trial_episodes - 1)]
            run_trial(agent, system, adapt, sample=True)
            last = run_trial(agent, system, [np.random.SeedSequence([args.eval_seed, 0])], sample=False)
            scores.append(sum(last.rewards))
    return float(np.mean(scores))


@dataclass
class Demo:
    """One demonstrated trial on one city: per step the model's inputs and MPC's distribution."""

    city: str
    x: list[torch.Tensor]  # (N, F) each
    prev_action: list[torch.Tensor]  # (N,)
    prev_reward: list[torch.Tensor]  # ()
    target: list[torch.Tensor]  # (N,) MPC's desired share of the idle fleet per region
    returns: torch.Tensor  # (S,) discounted scaled returns over the trial


def demonstrate(args: Args, systems: dict[str, FleetSystem]) -> list[Demo]:
    """MPC-Forecast trials (``trial_episodes`` episodes each) on every training city, training streams."""
    from marl_amod.baselines.mpc import MPCForecast

    demos, mpc = [], MPCForecast()
    for c, name in enumerate(args.cities):
        system, scale = systems[name], CityScale.of(systems[name].city)
        n = system.city.n_regions
        for trial in range(args.bc_trials):
            demo, rewards = Demo(name, [], [], [], [], torch.zeros(0)), []
            for k in range(args.trial_episodes):
                episode = 10**6 + (c * args.bc_trials + trial) * args.trial_episodes + k  # apart from the RL² streams
                system.reset(train_seed(args.seed, episode))
                mpc.reset(system, np.random.default_rng([args.seed, episode]))
                prev_a, prev_r = torch.zeros(n), torch.zeros(())
                while not system.done:
                    target = mpc.target(system).astype(np.float64)
                    share = target / target.sum() if target.sum() > 0 else np.full(n, 1.0 / n)
                    demo.x.append(torch.as_tensor(task_features(system, scale, args.lookahead)))
                    demo.prev_action.append(prev_a), demo.prev_reward.append(prev_r), demo.target.append(torch.as_tensor(share, dtype=torch.float32))
                    r = system.step(system.targets_from_weights(share)).reward / scale.reward
                    prev_a, prev_r = torch.as_tensor(share * n, dtype=torch.float32), torch.tensor(r, dtype=torch.float32)
                    rewards.append(r)
            demo.returns = advantages(rewards, torch.zeros(len(rewards)), args.gamma, 1.0)[1]
            demos.append(demo)
    return demos


def imitate(model: RecurrentGNN, demos: list[Demo], args: Args, systems: dict[str, FleetSystem]) -> float:
    """Fit the policy to MPC's distributions (Dirichlet NLL) and the critic to the returns; last epoch's loss."""
    opt = torch.optim.Adam(model.parameters(), lr=args.bc_lr)
    edges = {name: torch.as_tensor(np.array(s.city.edge_index), dtype=torch.long) for name, s in systems.items()}
    order = np.random.default_rng([args.seed, 23])
    for _ in range(args.bc_epochs):
        total = 0.0
        for i in order.permutation(len(demos)):
            demo = demos[i]
            memory = model.initial_memory(demo.x[0].shape[0])
            nll, values = [], []
            for x, a, r, y in zip(demo.x, demo.prev_action, demo.prev_reward, demo.target, strict=True):
                alpha, v, memory = model(x, a, r, memory, edges[demo.city])
                y = y.clamp_min(1e-3)
                nll.append(-dirichlet(alpha).log_prob(y / y.sum()) / x.shape[0])  # per region: cities differ in N
                values.append(v)
            loss = torch.stack(nll).mean() + args.value_coef * F.smooth_l1_loss(torch.stack(values), demo.returns)
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), args.max_grad_norm)
            opt.step()
            total += loss.item()
    return total / max(len(demos), 1)


def train(args: Args, *, resume: str | None = None, progress: C.Progress | None = None, config_path: str | None = None) -> dict[str, Any]:
    """Meta-train over trials on the training cities, keep the best validated model, write its card."""
    _check_tasks(args)
    torch.set_num_threads(args.threads)
    C.seed_everything(args.seed)
    systems = {name: FleetSystem(load_city(name)) for name in dict.fromkeys([*args.cities, *args.val_cities])}
    model = RecurrentGNN(n_task_features(args.lookahead), args.hidden, args.conv)
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    rng = np.random.default_rng([args.seed, 17])  # which city each trial draws

    start_ep, prior_wall, best = 0, 0.0, C.BestActor.of(model)
    if resume:
        st = C.load_state(resume, "meta")
        model.load_state_dict(st["model"]), opt.load_state_dict(st["opt"])
        start_ep, prior_wall, best = st["episode"], st["wall_s"], C.BestActor(st["best_val"], st["best_actor"])
        rng.bit_generator.state = st["city_rng"]
    log = C.Logger(args.run_dir, resume_from=start_ep if resume else None)
    timer = C.Timer(prior_wall)
    done_ep = ep = start_ep
    if args.bc_trials and not resume:
        demos = demonstrate(args, systems)
        log.log(0, **{"bc/loss": imitate(model, demos, args, systems), "bc/episodes": len(demos) * args.trial_episodes})
        best = C.BestActor(validate(model, args, systems), copy.deepcopy(model.state_dict()))
        log.log(0, **{"eval/scaled_return": best.value, "time/wall_s": timer()})

    def save() -> tuple[Path, int]:
        path = C.state_path(args)
        C.save_state(path, algorithm="meta", model=model.state_dict(), opt=opt.state_dict(), episode=done_ep,
                     best_val=best.value, best_actor=best.state, wall_s=timer(), city_rng=rng.bit_generator.state)  # fmt: skip
        return path, done_ep

    with C.interruptible(save):
        while ep < args.episodes:
            losses, profits, rewards = [], [], []
            for _ in range(args.trials_per_update):
                name = args.cities[int(rng.integers(len(args.cities)))]
                system = systems[name]
                agent = MetaAgent(model, system.city, args.lookahead)
                seeds = [train_seed(args.seed, ep + k) for k in range(args.trial_episodes)]
                trial = run_trial(agent, system, seeds, sample=True)
                ep += args.trial_episodes
                values = torch.stack(trial.values)  # (S,) S = trial_episodes x horizon
                adv, target = advantages(trial.rewards, values, args.gamma, args.gae_lambda)
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
                loss = (-(torch.stack(trial.logps) * adv).mean() + args.value_coef * F.smooth_l1_loss(values, target)
                        - args.entropy_coef * torch.stack(trial.entropies).mean())  # fmt: skip
                losses.append(loss)
                profits.append(trial.profits[-1] / (system.city.horizon * agent.scale.reward))
                rewards.append(float(np.mean(trial.rewards)))
            opt.zero_grad()
            total = torch.stack(losses).mean()
            total.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), args.max_grad_norm)
            opt.step()
            done_ep = ep

            stats = {"train/last_episode_scaled_profit": float(np.mean(profits)), "train/scaled_reward": float(np.mean(rewards)),
                     "loss/total": total.item()}  # fmt: skip
            per_update = args.trials_per_update * args.trial_episodes
            if ep // args.eval_every != (ep - per_update) // args.eval_every or ep >= args.episodes:
                stats["eval/scaled_return"] = val = validate(model, args, systems)
                if val > best.value:
                    best = C.BestActor(val, copy.deepcopy(model.state_dict()))
                save()
            stats["time/wall_s"] = timer()
            log.log(ep, **stats)
            if progress is not None:
                progress(ep, args.episodes, stats)
            if args.time_limit_s and timer() > args.time_limit_s:
                break

    log.close()
    model.load_state_dict(best.state)
    return _finish(args, model, timer(), ep, config_path)


def _finish(args: Args, model: RecurrentGNN, wall_s: float, episodes: int, config_path: str | None) -> dict[str, Any]:
    """Adapt to the held-out ``scenario`` and report there (report seeds), then the policy card."""
    from marl_amod.checkpoints import make_card, save_policy
    from marl_amod.evaluation import evaluate
    from marl_amod.files import write_json

    city = load_city(args.scenario)
    policy = adapt(model, city, args.trial_episodes - 1, args.lookahead, seed=args.final_eval_seed)
    result = evaluate(policy, city, args.final_eval_episodes, args.final_eval_seed)
    profit = result["metrics"]["profit"]
    card = make_card(
        scenario=city.name, n_regions=None, algorithm="meta", mode="centralised", actor="recurrent", conv=args.conv,
        hidden=args.hidden, n_features=n_task_features(args.lookahead), lookahead=args.lookahead, seed=args.seed,
        episodes_trained=episodes, eval_episodes=args.final_eval_episodes, eval_seed=args.final_eval_seed,
        profit_mean=profit["mean"], profit_std=profit["std"], served_demand_mean=result["metrics"]["served_demand"]["mean"],
        training_wall_s=round(wall_s, 1), torch_threads=torch.get_num_threads(), config=config_path,
        args=args.model_dump(mode="json"),
    ).to_dict()
    summary: dict[str, Any] = {"card": card, "result": result}
    if args.policy_out:
        summary["policy"] = str(save_policy(args.policy_out, model, card))
    Path(args.run_dir).mkdir(parents=True, exist_ok=True)
    write_json(Path(args.run_dir) / "final_eval.json", result)
    return summary


# --------------------------------------------------------------------------------------------
# Adaptation to a new city: K episodes with memory, no gradient step
# --------------------------------------------------------------------------------------------
def adapt_seed(seed: int, episode: int) -> np.random.SeedSequence:
    """Demand of adaptation episode k: neither a report stream (seed, k) nor a training stream."""
    return np.random.SeedSequence([seed, episode, 4243])


class MetaPolicy(WeightPolicy):
    """The recurrent policy after adaptation: every episode starts from the adapted memory."""

    def __init__(self, agent: MetaAgent, name: str = "meta-rl") -> None:
        self.agent, self.name = agent, name
        self.adapted = agent.memory.detach().clone()

    def reset(self, system: FleetSystem, rng: np.random.Generator) -> None:
        super().reset(system, rng)
        self.agent.memory = self.adapted.clone()
        self.agent.new_episode()
        self._last: float | None = None

    @torch.no_grad()
    def weights(self, system: FleetSystem) -> np.ndarray:
        totals = system.sim.totals
        booked = float((totals.revenue - totals.trip_cost - totals.rebalancing_cost).sum())
        if self._last is not None:  # the step just taken: its dispatch profit minus its rebalancing cost
            self.agent.observe(booked - self._last)
        self._last = booked
        return self.agent.act(system, sample=False)[0]


@torch.no_grad()
def adapt(model: RecurrentGNN, city: City, episodes: int, lookahead: int, seed: int = 0) -> MetaPolicy:
    """Run ``episodes`` adaptation episodes in ``city`` (memory carried, no gradient) -> the policy."""
    model.eval()
    agent = MetaAgent(model, city, lookahead)
    run_trial(agent, FleetSystem(city), [adapt_seed(seed, k) for k in range(episodes)], sample=True)
    return MetaPolicy(agent)


def load_meta(path: str | Path) -> tuple[RecurrentGNN, dict[str, Any]]:
    """The recurrent model of a meta-RL policy file and its card (the weights checked against it)."""
    from marl_amod.checkpoints import _card_of, _read_blob
    from marl_amod.errors import DataError

    path = Path(path)
    blob = _read_blob(path)
    card = _card_of(path, blob["card"]).to_dict()
    if card["algorithm"] != "meta":
        raise DataError(f"{path} is a {card['algorithm']} policy, not a meta-RL one")
    model = RecurrentGNN(card["n_features"], card["hidden"], card["conv"])
    try:
        model.load_state_dict(blob["state_dict"])
    except RuntimeError as exc:
        raise DataError(f"{path}: weights do not fit its card: {str(exc).splitlines()[0]}") from None
    model.eval()
    return model, card


def load_policy(path: str | Path, city: City, episodes: int | None = None, seed: int = 0) -> MetaPolicy:
    """A meta-RL policy file adapted to ``city`` (``episodes`` adaptation episodes; default: the
    trial length it was trained with, minus one), ready for :func:`marl_amod.evaluation.evaluate`."""
    model, card = load_meta(path)
    k = card["args"]["trial_episodes"] - 1 if episodes is None else episodes
    policy = adapt(model, city, k, card["lookahead"], seed=seed)
    policy.name = Path(path).stem
    return policy
