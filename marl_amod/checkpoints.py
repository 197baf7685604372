"""Trained policies on disk: one :class:`PolicyCard` type, one writer, one careful reader.

A policy is ``x.pt`` (the actor's weights and its card) with two views of the card beside it:
``x.json`` for programs and ``x.md`` for people. Each file is written atomically
(:mod:`marl_amod.files`), the ``.pt`` first; the views record the SHA-256 of the ``.pt`` they
describe, so :func:`read_card` refuses a ``.json`` left over from another run (an interrupted
save, a copied file) instead of reporting another policy's numbers. The ``.pt`` carries its own
card and is the authority.

``load_policy(path, city)`` returns an :class:`ActorPolicy` that runs the actor deterministically
(the Dirichlet mean; or, where the card asks for ``selection``, the best of sampled candidates by
the twin Q critic the file carries: :mod:`marl_amod.selection`), so ``marl-amod evaluate --policy policies/x.pt`` treats a trained policy
exactly like a baseline; it is also a callable on the env's observations. A file that is empty, truncated, not a checkpoint, damaged, or whose
sizes do not fit the city is a :class:`DataError` naming the file and the problem.
"""

from __future__ import annotations

import hashlib
import io
import subprocess
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, ValidationError

from marl_amod.baselines.base import WeightPolicy, check_bound_city
from marl_amod.env import observations as ob
from marl_amod.env.features import n_features, node_features
from marl_amod.errors import ConfigError, DataError, pydantic_problems
from marl_amod.files import atomic_write, file_sha256, write_json
from marl_amod.models.distributions import dirichlet_mean
from marl_amod.scenario import City
from marl_amod.selection import QSelector, Selection
from marl_amod.system import FleetSystem

if TYPE_CHECKING:
    from marl_amod.ensemble import Adaptation

FORMAT = "marl_amod.policy/2"
REGION_BOUND = ("mlp", "cnn")  # actors whose weights are tied to the city's region count


class PolicyCard(BaseModel):
    """What a policy is and how it was made; the same type for native and RLlib trainers.

    Algorithm-specific facts (episodes trained, RLlib iterations, ...) ride along as extra fields.
    Fields added in format 2 are optional so format-1 cards (no env version, no commit) still load.
    """

    model_config = ConfigDict(extra="allow")

    scenario: str
    algorithm: str
    mode: str
    actor: str
    conv: str
    hidden: int
    readout: str | None = None
    """the GNN actor's fleet-wide readout (``readout``); absent: none, the paper's actor"""
    agent_id: bool | None = None
    """the GNN actor appends a one-hot region identity to every node (``agent_id``): it runs only
    on cities of ``n_regions`` regions; absent: no identity, the paper's actor"""
    standardise_inputs: bool | None = None
    """the MLP actor standardises its inputs by statistics carried in its weights; absent: it does not"""
    n_features: int
    lookahead: int
    seed: int
    time_context: bool = False
    """the actor also reads the 3 time values (time of day, step fraction) on every node (``actor_time``)"""
    arrivals_now: bool | None = None
    """the node features end with the vehicles arriving now (``arrivals_now``, :mod:`marl_amod.env.features`);
    absent: the paper's features"""
    env_version: str | None = None
    """the env module the policy was trained on: amod_v0 -> "v0" (results change with it)"""
    n_regions: int | None = None
    """regions of the training city (MLP and CNN actors only run on cities of this size)"""
    eval_episodes: int | None = None
    eval_seed: int | None = None
    profit_mean: float | None = None
    profit_std: float | None = None
    served_demand_mean: float | None = None
    training_wall_s: float | None = None
    config: str | None = None
    """the config file that reproduces the run"""
    args: dict[str, Any] | None = None
    """the validated training arguments (after the config's extends: and defaults)"""
    git_commit: str | None = None
    """the code's commit when trained (with +dirty if the tree had changes)"""
    platform: dict[str, str] | None = None
    """what computed it (:func:`platform_info`): the same config and code repeat a run to the bit on one
    platform, not across CPUs (docs/meta/log.md, "The tables' pair again, in one command")"""
    critic: dict[str, Any] | None = None
    """the twin Q critic whose weights the file carries beside the actor's (IQL, CQL):
    n_features, hidden, conv; absent: the file has the actor only"""
    selection: Selection | None = None
    """Q-guided action selection (:mod:`marl_amod.selection`); absent: the Dirichlet mean"""

    def to_dict(self) -> dict[str, Any]:
        return self.model_dump(exclude_none=True)


def env_version() -> str:
    """The env's version tag from its versioned name: ``amod_v0`` -> ``v0`` (it changes whenever
    learning results could)."""
    from marl_amod.env import ENV_VERSION

    return ENV_VERSION.rsplit("_", 1)[-1]


def git_commit() -> str | None:
    """The commit of the code being run (None outside a git checkout)."""
    root = Path(__file__).resolve().parent.parent
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root, capture_output=True, text=True, timeout=5).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    return f"{sha}+dirty" if dirty.strip() else sha


def platform_info() -> dict[str, str]:
    """The versions and CPU a run's floating-point results depend on: torch and numpy, the CPU kernels
    torch dispatches to (``get_cpu_capability``: AVX2, AVX512, ...) and the CPU's model name. Why: the
    tables' meta-policy retrained from its configs on another machine came out with other weights,
    while the same code repeated itself to the bit on one machine, old code and new alike."""
    import platform

    import numpy as np
    import torch

    model = ""
    try:
        model = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("model name")), "")
    except OSError:
        pass
    return {"torch": torch.__version__, "numpy": np.__version__, "cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "cpu": model or platform.processor() or platform.machine()}  # fmt: skip


def make_card(**fields: Any) -> PolicyCard:
    """A card for a policy trained now: env version, commit and platform filled in."""
    return PolicyCard(env_version=env_version(), git_commit=git_commit(), platform=platform_info(), **fields)


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------
def training_scenario(card: dict[str, Any] | PolicyCard) -> str:
    """The scenario to load the card's city from: its training ``args.scenario`` as given (a YAML
    path for a user's scenario, whose city name ``scenario`` is no bundled name), else ``scenario``."""
    card = card.to_dict() if isinstance(card, PolicyCard) else card
    return str((card.get("args") or {}).get("scenario") or card["scenario"])


def card_markdown(path: Path, card: dict[str, Any]) -> str:
    """The human-readable view of the card of policy ``path`` (policies/x.md)."""
    lines = [f"# Policy `{path.stem}`", "", "| field | value |", "|---|---|"]
    for k, v in card.items():
        if k == "args":
            continue
        if isinstance(v, float):
            v = f"{v:,.2f}"
        lines.append(f"| {k} | {v} |")
    if card.get("reproduce"):  # a policy made by more than one training run (DAgger)
        lines += ["", f"Reproduce: `{card['reproduce']}`"]
    elif card.get("config"):
        config = card["config"]
        if "/compare/" in config or Path(config).stem.startswith("compare"):
            lines += ["", f"Reproduce: `marl-amod compare --config {config}` (trains it when the file is missing)"]
        else:
            backend = " --backend rllib" if str(card.get("algorithm", "")).startswith("rllib") else ""
            lines += ["", f"Reproduce: `marl-amod train{backend} --config {config}`"]
    lines += ["", f"Evaluate: `marl-amod evaluate --scenario {training_scenario(card)} --policy {path} --episodes 10`", ""]
    return "\n".join(lines)


def write_policy(
    path: str | Path, state_dict: dict[str, torch.Tensor], card: PolicyCard | dict[str, Any], critic_state: dict[str, torch.Tensor] | None = None
) -> Path:
    """Write ``path`` (.pt: weights + card, and the critic's weights when given), then its .json
    and .md views, each atomically.

    The views name the SHA-256 of the .pt bytes, so a reader can tell a view from another run.
    """
    card = card if isinstance(card, PolicyCard) else PolicyCard.model_validate(card)
    path = Path(path).with_suffix(".pt")
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = {"format": FORMAT, "card": card.to_dict(), "state_dict": _detached(state_dict)}
    if critic_state is not None:
        blob["critic_state_dict"] = _detached(critic_state)
    buffer = io.BytesIO()
    torch.save(blob, buffer)
    data = buffer.getvalue()
    atomic_write(path, data)
    view = {**card.to_dict(), "pt_sha256": hashlib.sha256(data).hexdigest()}
    write_json(path.with_suffix(".json"), view)
    atomic_write(path.with_suffix(".md"), card_markdown(path, view))
    return path


def _detached(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: v.detach().cpu().clone() for k, v in state.items()}


def save_policy(path: str | Path, actor: torch.nn.Module, card: PolicyCard | dict[str, Any], critic: torch.nn.Module | None = None) -> Path:
    """Write an actor's policy file (with ``critic``'s weights when given) and its card views
    (see :func:`write_policy`)."""
    return write_policy(path, actor.state_dict(), card, None if critic is None else critic.state_dict())


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------
def check_torch_file(path: Path, what: str = "policy checkpoint") -> None:
    """Raise a DataError saying in plain words why ``path`` is not an intact torch file.

    Checked before ``torch.load``, whose errors on damaged files are cryptic (or a crash).
    """
    if not path.is_file():
        raise ConfigError(f"{what} {path} not found")
    if path.stat().st_size == 0:
        raise DataError(f"{path} is empty (0 bytes): an interrupted copy? Copy or train it again")
    if not zipfile.is_zipfile(path):
        head = path.read_bytes()[:64]
        if head.startswith(b"PK"):
            kind = "truncated (the archive's end record is missing: an interrupted save or copy?)"
        else:
            kind = "a text file" if head.isascii() else "not a torch checkpoint"
        raise DataError(f"{path} is not a {what}: {kind} (a torch .pt file is a zip archive)")
    try:
        with zipfile.ZipFile(path) as zf:
            bad = zf.testzip()  # CRC of every member: catches bit flips and partial copies
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        raise DataError(f"{path} is damaged: {exc}") from None
    if bad is not None:
        raise DataError(f"{path} is damaged: {bad} fails its checksum (a bit flip or a partial copy)")


def _read_blob(path: Path) -> dict[str, Any]:
    """The checkpoint's dict, or a DataError saying in plain words why the file is not one."""
    check_torch_file(path)
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many types for bad files; all mean the same here
        raise DataError(f"{path} cannot be read as a policy checkpoint: {str(exc).splitlines()[0]}") from None
    if not isinstance(blob, dict) or not isinstance(blob.get("state_dict"), dict) or not isinstance(blob.get("card"), dict):
        raise DataError(f"{path} is not a marl_amod policy checkpoint (it has no card and state_dict)")
    return blob


def _card_of(path: Path, raw: dict[str, Any]) -> PolicyCard:
    try:
        return PolicyCard.model_validate(raw)
    except ValidationError as exc:
        raise DataError(f"{path}: its card is incomplete ({pydantic_problems(exc, {'missing': 'missing'})})") from None


def read_card(path: str | Path) -> dict[str, Any]:
    """The card of policy ``path`` from its .json view, checked to describe this very .pt."""
    path = Path(path).with_suffix(".pt")
    view = path.with_suffix(".json")
    if not view.is_file():
        return _card_of(path, _read_blob(path)["card"]).to_dict()
    from marl_amod.data import read_json

    card = read_json(view)
    expected = card.pop("pt_sha256", None)
    if expected is not None and path.is_file() and file_sha256(path) != expected:
        raise DataError(f"{view} describes another version of {path.name} (an interrupted save or a copied file): retrain, or delete the .json")
    return card


def _trained_regions(kind: str, card: PolicyCard, state: dict[str, torch.Tensor]) -> int:
    if card.n_regions is not None:
        return card.n_regions
    if kind == "cnn":
        return int(state["cells"].numel()) if "cells" in state else -1
    weights = [v for k, v in state.items() if k.endswith("weight")]
    return int(weights[-1].shape[0]) if weights else -1  # the MLP's output layer has one unit per region


def load_actor(path: str | Path, city: City) -> tuple[torch.nn.Module, dict[str, Any]]:
    """Rebuild the actor of a policy file for ``city``; returns (actor in eval mode, card)."""
    from marl_amod.models import build_actor

    path = Path(path)
    blob = _read_blob(path)
    card, state = _card_of(path, blob["card"]), blob["state_dict"]
    expected_f = n_features(card.lookahead, bool(card.arrivals_now))
    if card.n_features != expected_f:
        raise DataError(f"{path}: card says lookahead {card.lookahead}, arrivals_now {bool(card.arrivals_now)} but {card.n_features} features "
                        f"(expected {expected_f})")  # fmt: skip
    if card.agent_id and card.n_regions != city.n_regions:
        raise DataError(
            f"{path}: trained with agent_id (a one-hot identity of each of {card.n_regions} regions); {city.name} has "
            f"{city.n_regions}: a region-identity policy runs only on a city of its training city's size and order"
        )
    if card.actor in REGION_BOUND:
        trained = _trained_regions(card.actor, card, state)
        if trained != city.n_regions:
            raise DataError(
                f"{path}: trained for {trained} regions; {city.name} has {city.n_regions}; "
                "MLP and CNN actors are tied to a region count — use a GNN policy"
            )
    try:
        actor = build_actor(
            card.actor, city, actor_inputs(card.n_features, card.time_context), card.hidden, card.conv, card.readout or "none", bool(card.agent_id),
            bool(card.standardise_inputs),
        )
    except ValueError as exc:
        raise DataError(f"{path}: {exc}") from None
    expected = actor.state_dict()
    missing, unexpected = sorted(set(expected) - set(state)), sorted(set(state) - set(expected))
    if missing or unexpected:
        raise DataError(f"{path}: weights are not a {card.actor} actor's (missing {missing[:3]}, unexpected {unexpected[:3]})")
    for key, value in expected.items():
        if tuple(state[key].shape) != tuple(value.shape):
            raise DataError(
                f"{path}: weights do not fit its card (hidden {card.hidden}, lookahead {card.lookahead} = {card.n_features} features): "
                f"{key} is {tuple(state[key].shape)} in the file, {tuple(value.shape)} expected"
            )
    actor.load_state_dict(state)
    actor.eval()
    return actor, card.to_dict()


def load_critic(path: str | Path) -> tuple[torch.nn.Module, dict[str, Any]]:
    """The twin Q critic a policy file carries (IQL, CQL); returns (critic in eval mode, card).
    A file without one is a DataError: only the actor was saved, so nothing can score actions."""
    from marl_amod.models import TwinQ

    path = Path(path)
    blob = _read_blob(path)
    card, state = _card_of(path, blob["card"]), blob.get("critic_state_dict")
    if card.critic is None or not isinstance(state, dict):
        raise DataError(f"{path} carries no critic weights (only IQL and CQL policies trained with them do): "
                        "Q-guided selection needs them; retrain the policy, or drop selection")  # fmt: skip
    try:
        critic = TwinQ(card.critic["n_features"], card.critic["hidden"], card.critic["conv"])
        critic.load_state_dict(state)
    except (KeyError, ValueError, RuntimeError) as exc:
        raise DataError(f"{path}: its critic weights do not fit its card's critic {card.critic}: {str(exc).splitlines()[0]}") from None
    return critic.eval(), card.to_dict()


def architecture_args(card: Mapping[str, Any]) -> dict[str, Any]:
    """The run arguments that rebuild a card's actor: a run warm-started from the policy
    (fine-tuning, transfer) must set exactly these, or its actor's shapes differ."""
    return {
        "actor": card["actor"], "conv": card["conv"], "readout": card.get("readout") or "none",
        "agent_id": bool(card.get("agent_id")), "standardise_inputs": bool(card.get("standardise_inputs")), "hidden": card["hidden"],
        "lookahead": card["lookahead"], "actor_time": card.get("time_context", False), "arrivals_now": bool(card.get("arrivals_now")),
    }  # fmt: skip


def feature_args(card: Mapping[str, Any]) -> dict[str, Any]:
    """What a card's actor reads (``lookahead``, ``time_context``, ``arrivals_now``), as the
    keywords of :class:`ActorPolicy` and ``evaluate_actor``: a policy rebuilt from a file sees the
    features it was trained on."""
    return {"lookahead": card["lookahead"], "time_context": bool(card.get("time_context")), "arrivals_now": bool(card.get("arrivals_now"))}


def actor_inputs(n_node_features: int, time_context: bool) -> int:
    """Input columns of an actor: the node features F, plus the 3 time values with ``time_context``."""
    return n_node_features + ob.N_CONTEXT if time_context else n_node_features


def with_context(x: torch.Tensor, ctx: torch.Tensor) -> torch.Tensor:
    """Node features x (..., N, F) with the time values ctx (..., 3) appended to every node: (..., N, F + 3);
    one function, so training and evaluation feed a time-aware actor (and critic) the same input."""
    ctx = torch.as_tensor(ctx, dtype=x.dtype)
    return torch.cat([x, ctx.unsqueeze(-2).expand(*x.shape[:-1], ctx.shape[-1])], dim=-1)


class ActorPolicy(WeightPolicy):
    """Runs an actor deterministically: weights = Dirichlet mean of its concentrations.

    It is also a callable on the env's observations (PettingZoo convention: observations dict
    -> actions dict), so a trained policy runs wherever an outside one does (``record_episode``,
    ``marl_amod.evaluate``). Both paths feed the actor the same node features: each agent's
    observation begins with its region's row of them, followed by the time values that a
    ``time_context`` actor reads as well.
    """

    def __init__(
        self, actor: torch.nn.Module, city: City, lookahead: int = 6, name: str = "actor", time_context: bool = False,
        selector: QSelector | None = None, arrivals_now: bool = False,
    ) -> None:
        self.actor, self.lookahead, self.name, self.time_context, self.selector = actor, lookahead, name, time_context, selector
        self.arrivals_now = arrivals_now
        self.min_degree = ob.max_in_degree(city)  # the env's neighbour slots: this many, or more when padded
        self.edge_index = torch.tensor(np.array(city.edge_index), dtype=torch.long)
        self.agents = ob.agent_names(city.n_regions)
        self.city = city

    def reset(self, system: FleetSystem, rng: np.random.Generator) -> None:
        check_bound_city(self.name, self.city, system)
        super().reset(system, rng)

    def weights(self, system: FleetSystem) -> np.ndarray:
        return self._mean(node_features(system, self.lookahead, arrivals_now=self.arrivals_now), ob.time_features(system.city, system.t))

    def __call__(self, observations: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Actions (each agent's weight, shape (1,)) for the env's local observations."""
        stacked = np.stack([np.asarray(observations[a], dtype=np.float32) for a in self.agents])
        f = n_features(self.lookahead, self.arrivals_now)
        try:
            own, ctx, neighbours, _ = ob.split_local(stacked, f)  # (N, F), (N, 3), (N, K, F)
        except ValueError:  # the layout does not fit this F
            neighbours = None
        if neighbours is None or neighbours.shape[-2] < self.min_degree:  # another F: no fit, or a fit with the wrong columns
            raise ConfigError(f"{self.name} reads the env's observations with lookahead {self.lookahead}, arrivals_now {self.arrivals_now} "
                              f"(F = {f}); these ({stacked.shape[-1]} values) are another env's: make it with the same options")  # fmt: skip
        w = self._mean(own, ctx[0]).astype(np.float32)  # exact: the weights are float32 values
        return {a: w[i : i + 1] for i, a in enumerate(self.agents)}

    @torch.no_grad()
    def _mean(self, features: np.ndarray, ctx: np.ndarray) -> np.ndarray:
        x = torch.as_tensor(features)
        alpha = self.actor(with_context(x, ctx) if self.time_context else x, self.edge_index)  # (N,)
        mean = dirichlet_mean(alpha).numpy().astype(np.float64)
        return mean if self.selector is None else self.selector(features, mean)


def _selection(raw: Selection | dict[str, Any] | None) -> Selection | None:
    try:
        return None if raw is None else Selection.model_validate(raw)
    except ValidationError as exc:
        raise ConfigError(f"selection: {pydantic_problems(exc)}") from None


def load_policy(
    path: str | Path, city: City | str | None = None, selection: Selection | dict[str, Any] | None = None, adaptation: Adaptation | None = None
) -> WeightPolicy:
    """A deterministic policy from a checkpoint, for ``city`` (a City or a scenario name; default:
    the scenario on its card). It runs on the simulator and as a callable on env observations; a
    meta-RL policy (algorithm "meta") runs its adaptation episodes in ``city`` first, played by
    ``adaptation`` (default: as its card says; :func:`marl_amod.algos.meta.adapt`).

    ``selection`` (default: the card's) picks each action among candidates by the file's critic
    (:mod:`marl_amod.selection`); ``{"candidates": 0, ...}`` turns a card's selection off.
    An ensemble file (:mod:`marl_amod.ensemble`) gives its members' mean, each member loaded so
    (its meta-policies adapting by the file's ``adaptation`` where it names one)."""
    from marl_amod.ensemble import is_ensemble, load_ensemble, read_members, read_spec

    if is_ensemble(path):
        spec = read_spec(path)
        adaptation = spec.adaptation or adaptation  # write_ensemble refuses it (and together) where a member is no meta-policy
        if spec.together:  # meta-policies adapting as one (the city, by default, the first member's)
            from marl_amod.algos import meta
            from marl_amod.scenario import load_city

            if not isinstance(city, City):
                first = read_members(path)[0]
                city = load_city(city if city is not None else training_scenario(_card_of(first, _read_blob(first)["card"])))
            return meta.load_policy(path, city, adaptation=adaptation)
        return load_ensemble(path, lambda member: load_policy(member, city, selection, adaptation))
    card = _card_of(Path(path), _read_blob(Path(path))["card"])
    if not isinstance(city, City):
        from marl_amod.scenario import load_city

        city = load_city(city if city is not None else training_scenario(card))
    if card.algorithm in ("meta", "meta-bc"):  # a recurrent meta-policy: adapt to the city first (no gradient step)
        from marl_amod.algos import meta

        return meta.load_policy(path, city, adaptation=adaptation)
    actor, card = load_actor(path, city)
    chosen = _selection(selection if selection is not None else card.get("selection"))
    selector = QSelector(load_critic(path)[0], city, chosen) if chosen is not None and chosen.candidates else None
    return ActorPolicy(actor, city, name=Path(path).stem, selector=selector, **feature_args(card))
