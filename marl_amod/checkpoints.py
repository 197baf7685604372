"""Trained policies on disk: a small torch file (actor weights + card) and a JSON/markdown card.

``load_policy(path, city)`` returns an :class:`ActorPolicy` that runs the actor deterministically
(the Dirichlet mean), so ``marl-amod evaluate --policy policies/x.pt`` treats a trained policy
exactly like a baseline and writes the same JSON; it is also a callable on the env's observations.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from marl_amod.baselines.base import WeightPolicy
from marl_amod.env import observations as ob
from marl_amod.env.features import node_features
from marl_amod.errors import ConfigError
from marl_amod.scenario import City
from marl_amod.system import FleetSystem

CARD_KEYS = ("scenario", "algorithm", "mode", "actor", "conv", "hidden", "n_features", "lookahead", "seed")


def save_policy(path: str | Path, actor: torch.nn.Module, card: dict[str, Any]) -> Path:
    """Write ``path`` (.pt: actor state dict + card) and ``path`` with .json beside it."""
    missing = [k for k in CARD_KEYS if k not in card]
    if missing:
        raise ValueError(f"policy card lacks {missing}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().clone() for k, v in actor.state_dict().items()}
    torch.save({"format": "marl_amod.policy/1", "card": card, "state_dict": state}, path)
    path.with_suffix(".json").write_text(json.dumps(card, indent=2, default=float) + "\n")
    return path


def write_card_markdown(path: str | Path, card: dict[str, Any]) -> Path:
    """A human-readable card next to the checkpoint (policies/x.md)."""
    path = Path(path).with_suffix(".md")
    lines = [f"# Policy `{Path(path).stem}`", "", "| field | value |", "|---|---|"]
    for k, v in card.items():
        if isinstance(v, float):
            v = f"{v:,.2f}"
        lines.append(f"| {k} | {v} |")
    if "config" in card:
        backend = " --backend rllib" if str(card.get("algorithm", "")).startswith("rllib") else ""
        lines += ["", f"Reproduce: `marl-amod train{backend} --config {card['config']}`"]
    lines += ["", f"Evaluate: `marl-amod evaluate --scenario {card['scenario']} --policy {Path(path).with_suffix('.pt')} --episodes 10`", ""]
    path.write_text("\n".join(lines))
    return path


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The checked contents of a policy file: ``card`` and ``state_dict``."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"policy checkpoint {path} not found")
    blob = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(blob, dict) or "state_dict" not in blob:
        raise ConfigError(f"{path} is not a marl_amod policy checkpoint")
    return blob


def load_actor(path: str | Path, city: City) -> tuple[torch.nn.Module, dict[str, Any]]:
    """Rebuild the actor of a policy file for ``city``; returns (actor in eval mode, card)."""
    from marl_amod.models import build_actor

    blob = read_checkpoint(path)
    card = blob["card"]
    actor = build_actor(card["actor"], city, card["n_features"], card["hidden"], card["conv"])
    actor.load_state_dict(blob["state_dict"])
    actor.eval()
    return actor, card


class ActorPolicy(WeightPolicy):
    """Runs an actor deterministically: weights = Dirichlet mean of its concentrations.

    It is also a callable on the env's observations (PettingZoo convention: observations dict
    -> actions dict), so a trained policy runs wherever an outside one does (``record_episode``,
    ``marl_amod.evaluate``). Both paths feed the actor the same node features: each agent's
    observation begins with its region's row of them.
    """

    def __init__(self, actor: torch.nn.Module, city: City, lookahead: int = 6, name: str = "actor") -> None:
        self.actor, self.lookahead, self.name = actor, lookahead, name
        self.edge_index = torch.as_tensor(city.edge_index, dtype=torch.long)
        self.agents = ob.agent_names(city.n_regions)

    def weights(self, system: FleetSystem) -> np.ndarray:
        return self._mean(node_features(system, self.lookahead))

    def __call__(self, observations: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Actions (each agent's weight, shape (1,)) for the env's local observations."""
        stacked = np.stack([np.asarray(observations[a], dtype=np.float32) for a in self.agents])
        own = ob.split_local(stacked, ob.n_features(self.lookahead))[0]  # (N, F)
        w = self._mean(own).astype(np.float32)  # exact: the weights are float32 values
        return {a: w[i : i + 1] for i, a in enumerate(self.agents)}

    @torch.no_grad()
    def _mean(self, features: np.ndarray) -> np.ndarray:
        alpha = self.actor(torch.as_tensor(features), self.edge_index)  # (N,)
        return (alpha / alpha.sum()).numpy().astype(np.float64)


def load_policy(path: str | Path, city: City | str | None = None) -> ActorPolicy:
    """A deterministic policy from a checkpoint, for ``city`` (a City or a scenario name; default:
    the scenario on its card). It runs on the simulator and as a callable on env observations."""
    if not isinstance(city, City):
        from marl_amod.scenario import load_city

        city = load_city(city if city is not None else read_checkpoint(path)["card"]["scenario"])
    actor, card = load_actor(path, city)
    return ActorPolicy(actor, city, card["lookahead"], name=Path(path).stem)


def update_card(path: str | Path, **fields: Any) -> dict[str, Any]:
    """Add fields (e.g. the config that reproduces the run) to a policy's card in .pt, .json and .md."""
    path = Path(path)
    blob = torch.load(path, map_location="cpu", weights_only=True)
    blob["card"].update(fields)
    torch.save(blob, path)
    path.with_suffix(".json").write_text(json.dumps(blob["card"], indent=2, default=float) + "\n")
    write_card_markdown(path, blob["card"])
    return blob["card"]
