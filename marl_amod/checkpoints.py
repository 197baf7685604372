"""Trained policies on disk: a small torch file (actor weights + card) and a JSON/markdown card.

``load_policy(path, city)`` returns a :class:`~marl_amod.baselines.WeightPolicy` that runs the
actor deterministically (the Dirichlet mean), so ``marl-amod evaluate --policy policies/x.pt``
treats a trained policy exactly like a baseline and writes the same JSON.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from marl_amod.baselines import WeightPolicy
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


def load_actor(path: str | Path, city: City) -> tuple[torch.nn.Module, dict[str, Any]]:
    """Rebuild the actor of a policy file for ``city``; returns (actor in eval mode, card)."""
    from marl_amod.models import build_actor

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"policy checkpoint {path} not found")
    blob = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(blob, dict) or "state_dict" not in blob:
        raise ConfigError(f"{path} is not a marl_amod policy checkpoint")
    card = blob["card"]
    actor = build_actor(card["actor"], city, card["n_features"], card["hidden"], card["conv"])
    actor.load_state_dict(blob["state_dict"])
    actor.eval()
    return actor, card


class ActorPolicy(WeightPolicy):
    """Runs an actor deterministically: weights = Dirichlet mean of its concentrations."""

    def __init__(self, actor: torch.nn.Module, city: City, lookahead: int = 6, name: str = "actor") -> None:
        self.actor, self.lookahead, self.name = actor, lookahead, name
        self.edge_index = torch.as_tensor(city.edge_index, dtype=torch.long)

    @torch.no_grad()
    def weights(self, system: FleetSystem) -> np.ndarray:
        from marl_amod.env.features import node_features
        from marl_amod.models.distributions import dirichlet_mean

        x = torch.as_tensor(node_features(system, self.lookahead))  # (N, F)
        alpha = self.actor(x, self.edge_index)  # (N,)
        return dirichlet_mean(alpha).numpy().astype(np.float64)


def load_policy(path: str | Path, city: City) -> ActorPolicy:
    """A deterministic policy from a checkpoint, ready for :func:`marl_amod.evaluation.evaluate`."""
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
