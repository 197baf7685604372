"""Several weight policies acting as one: each step, the mean of their desired distributions.

Why: policies trained by one recipe from different seeds err differently where their training
never led them (a meta-policy's own states in a city it never saw: docs/meta/log.md, "An ensemble
of training seeds"); the mean of their distributions cancels the part of the error that differs.
Nothing is trained: the members are policy files, and the ensemble is a small YAML file beside
them that loads wherever a checkpoint does (``make_policy``, ``marl-amod evaluate --policy``,
``marl-amod transfer-table --meta-policy``)::

    # policies/meta_rl_l1_ensemble.yaml
    members: [meta_rl_l1_cities.pt, seeds/meta_rl_l1_cities_seed1.pt]
    adaptation: mean   # optional, meta-policies only: how they act in their adaptation episodes
    together: true     # optional, meta-policies only: they adapt as one (K episodes in all, not K each)

``marl-amod ensemble MEMBER.pt MEMBER.pt --out X.yaml`` writes the file and its card (``X.md``:
each member's card in a row). Member paths are relative to the file. A member that reads its own
last action (a meta-policy) is told the ensemble's action instead
(:meth:`~marl_amod.baselines.base.WeightPolicy.executed`), so its next step sees the fleet the
ensemble made. Each meta-policy adapts to the city alone, so an ensemble of m of them plays m
times its K adaptation episodes there; with ``together`` they adapt as the ensemble they will be
(:func:`marl_amod.algos.meta.adapt_together`): K episodes in all, each member's memory reading the
path the ensemble drove, which is the path it then acts on.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from marl_amod.baselines.base import WeightPolicy
from marl_amod.data import read_yaml
from marl_amod.errors import ConfigError, DataError, pydantic_problems
from marl_amod.system import FleetSystem

ENSEMBLE_SUFFIXES = (".yaml", ".yml")
Adaptation = Literal["sampled", "mean", "prior-concentration"]
"""How a meta-policy acts in its adaptation episodes (:func:`marl_amod.algos.meta.adapt`)."""


class EnsembleFile(BaseModel):
    """What an ensemble file holds: two or more policy files (relative to it) and, for meta-policies,
    how they act while adapting (None: as each was trained, sampled) and whether they adapt
    together (K episodes in all, played by the ensemble) or each alone (K each)."""

    model_config = ConfigDict(extra="forbid")
    members: list[str] = Field(min_length=2)
    adaptation: Adaptation | None = None
    together: bool = False


def is_ensemble(path: str | Path) -> bool:
    """Whether ``path`` names an ensemble file rather than a checkpoint."""
    return Path(path).suffix in ENSEMBLE_SUFFIXES


def read_spec(path: str | Path) -> EnsembleFile:
    """The ensemble file ``path``, validated (members not yet checked: :func:`read_members`)."""
    try:
        return EnsembleFile.model_validate(read_yaml(Path(path), what="ensemble"))
    except ValidationError as exc:
        raise ConfigError(f"ensemble {path}: {pydantic_problems(exc)}") from None


def read_members(path: str | Path) -> list[Path]:
    """The member checkpoints of the ensemble file ``path``, each checked to be there."""
    path = Path(path)
    spec = read_spec(path)
    members = [path.parent / m for m in spec.members]
    for m in members:
        if m.suffix != ".pt":
            raise ConfigError(f"ensemble {path}: member {m} is not a checkpoint (.pt); ensembles do not nest")
        if not m.is_file():
            raise ConfigError(f"ensemble {path}: member {m} not found")
    return members


class PolicyEnsemble(WeightPolicy):
    """The members' weights, each as shares of the idle fleet, averaged."""

    def __init__(self, members: list[WeightPolicy], name: str = "ensemble") -> None:
        if len(members) < 2:
            raise ConfigError(f"an ensemble needs two or more members, got {len(members)}")
        self.members, self.name = members, name

    def reset(self, system: FleetSystem, rng: np.random.Generator) -> None:
        super().reset(system, rng)
        for member in self.members:
            member.reset(system, rng)

    def weights(self, system: FleetSystem) -> np.ndarray:
        mean = np.mean([_shares(member, member.weights(system)) for member in self.members], axis=0)
        for member in self.members:
            member.executed(mean)
        return mean

    def __call__(self, observations: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The members' actions on the env's observations, each as shares, averaged (members that
        are callables on observations: the actor policies; a meta-policy reads the simulator)."""
        if not all(callable(m) for m in self.members):
            raise ConfigError(f"ensemble {self.name}: every member must act on the env's observations, "
                              f"and {', '.join(m.name for m in self.members if not callable(m))} reads the simulator: use marl_amod.evaluate")  # fmt: skip
        actions = [m(observations) for m in self.members]  # type: ignore[operator]
        agents = list(actions[0])
        mean = np.mean([_shares(m, np.concatenate([np.ravel(act[a]) for a in agents])) for m, act in zip(self.members, actions, strict=True)], axis=0)
        mean = mean.astype(np.float32)
        return {a: mean[i : i + 1] for i, a in enumerate(agents)}


def _shares(member: WeightPolicy, weights: np.ndarray) -> np.ndarray:
    """``weights`` as shares of the idle fleet; all zeros ("stay") has no share to average."""
    w = np.asarray(weights, dtype=np.float64)
    if not w.sum() > 0:
        raise DataError(f"ensemble member {member.name} asked every vehicle to stay (all-zero weights): an ensemble averages distributions")
    return w / w.sum()


def load_ensemble(path: str | Path, load_member: Callable[[Path], WeightPolicy]) -> PolicyEnsemble:
    """The ensemble of ``path``, each member built by ``load_member`` (which says for what city, and
    how a meta-policy adapts there)."""
    return PolicyEnsemble([load_member(m) for m in read_members(path)], name=Path(path).stem)


def write_ensemble(out: str | Path, members: list[str | Path], adaptation: Adaptation | None = None, together: bool = False) -> Path:
    """Write the ensemble file ``out`` (.yaml) of the checkpoints ``members`` (paths relative to it)
    and its card ``out.md``; each member is read first, so a file that is not a policy fails here
    (and ``adaptation`` or ``together`` is refused unless every member is a meta-policy)."""
    from marl_amod.checkpoints import read_card
    from marl_amod.files import atomic_write, check_destination

    out = Path(out)
    if out.suffix not in ENSEMBLE_SUFFIXES:
        raise ConfigError(f"ensemble {out}: name it .yaml")
    try:
        EnsembleFile(members=[str(m) for m in members], adaptation=adaptation, together=together)
    except ValidationError as exc:
        raise ConfigError(f"ensemble {out}: {pydantic_problems(exc)}") from None
    for m in members:  # before any card is read or anything written
        if Path(m).suffix != ".pt":
            raise ConfigError(f"ensemble {out}: member {m} is not a checkpoint (.pt); ensembles do not nest, and a card is not its policy")
    if len({Path(m).resolve() for m in members}) < len(members):
        raise ConfigError(f"ensemble {out}: a member is given twice; each member's distribution weighs once")
    cards = [read_card(m) for m in members]
    others = [str(m) for m, c in zip(members, cards, strict=True) if c["algorithm"] not in ("meta", "meta-bc")]
    for asked, what in ((adaptation is not None, "adaptation is how meta-policies act while they adapt"), (together, "together is how meta-policies adapt")):
        if asked and others:
            raise ConfigError(f"ensemble {out}: {what}; {', '.join(others)} are not meta-policies")
    check_destination(out, what="ensemble")  # its folder made here (a missing one failed in the atomic write, naming its temporary file)
    relative = [Path(os.path.relpath(Path(m).resolve(), out.resolve().parent)).as_posix() for m in members]
    atomic_write(out, "members:\n" + "".join(f"  - {r}\n" for r in relative) + (f"adaptation: {adaptation}\n" if adaptation else "")
                 + ("together: true\n" if together else ""))  # fmt: skip
    read_members(out)  # what loading will check, checked now
    card = out.with_suffix(".md")
    kept = card.read_text().partition(NOTES)[2] if card.is_file() else ""  # "" without the marker too
    atomic_write(card, ensemble_markdown(out, [str(m) for m in members], cards, adaptation, together) + (f"\n{NOTES}{kept}" if kept else ""))
    return out


NOTES = "<!-- notes: what follows is kept when marl-amod ensemble writes this card again -->"
"""Where an ensemble card's written notes (a score, where it is used) begin: generated text above, kept text below."""


def ensemble_markdown(path: Path, members: list[str], cards: list[dict[str, Any]], adaptation: Adaptation | None = None, together: bool = False) -> str:
    """The card of an ensemble: its members' cards side by side, training wall time summed."""
    fields = ("algorithm", "seed", "config", "updates", "training_wall_s", "eval_streams", "profit_mean")
    adapts = f" Its meta-policies act by `{adaptation}` in their adaptation episodes." if adaptation else ""
    adapts += " They adapt together: the ensemble plays K adaptation episodes in all, not K each." if together else ""
    lines = [f"# Policy ensemble `{path.stem}`", "", f"The mean of {len(members)} policies' desired distributions (`marl_amod.ensemble`).{adapts}", "",
             "| member | " + " | ".join(fields) + " |", "|---" * (len(fields) + 1) + "|"]  # fmt: skip
    for member, card in zip(members, cards, strict=True):
        cells = [f"{card[k]:,.2f}" if isinstance(card.get(k), float) else str(card.get(k, "-")) for k in fields]
        lines.append(f"| {member} | " + " | ".join(cells) + " |")
    wall = sum(float(card.get("training_wall_s") or 0.0) for card in cards)
    longest = max(float(c.get("training_wall_s") or 0.0) for c in cards)
    lines += ["", f"Training: {wall / 60:,.1f} min in all; {longest / 60:,.1f} min for the longest member (the wall time when the members "
              "train side by side, one core each).", "",
              f"Make: `marl-amod ensemble {' '.join(members)} --out {path}{f' --adaptation {adaptation}' if adaptation else ''}{' --together' if together else ''}`", "",
              f"Evaluate: `marl-amod evaluate --scenario {cards[0]['scenario']} --policy {path} --episodes 10`", ""]  # fmt: skip
    return "\n".join(lines)
