"""SAC's per-transition update: the faster forms compute what the plain PyTorch forms do.

``Learner.update`` runs the target side in inference mode (no autograd bookkeeping); that must
leave the update's numbers exactly as they were, so a shipped SAC config reruns bit for bit.
"""

from __future__ import annotations

import contextlib

import pytest
import torch

from marl_amod.algos import common as C
from marl_amod.algos import sac
from marl_amod.scenario import grid_city


def _reference_update(monkeypatch: pytest.MonkeyPatch) -> None:
    """The update as it was: no_grad for the target side."""
    # (torch.inference_mode(False), the dense graph's guard for its cached operators, does nothing there)
    monkeypatch.setattr(torch, "inference_mode", lambda mode=True: torch.no_grad() if mode else contextlib.nullcontext())


def _with_local(b: dict[str, torch.Tensor], k: int = 3) -> dict[str, torch.Tensor]:
    """A replay sample with the decentralised actor's local fields: own (B, N, F), k neighbours
    (B, N, k, F) (here the region's own features, rolled), mask (B, N, k)."""
    out = dict(b)
    for p in ("", "next_"):
        x = b[f"{p}x"]
        out[f"{p}own"] = x
        out[f"{p}nbrs"] = torch.stack([x.roll(j + 1, dims=1) for j in range(k)], dim=2)
        out[f"{p}mask"] = torch.ones(*x.shape[:2], k)
    return out


@pytest.mark.parametrize(
    "num_envs, precision, mode",  # dense (stacked critics), bf16, decentralised (SAGE critics, local actor), torch-geometric
    [(2, "fp32", "centralised"), (2, "bf16", "centralised"), (2, "fp32", "decentralised"), (1, "fp32", "centralised")],
)
def test_learner_update_matches_the_reference_update_on_fixed_inputs(monkeypatch, num_envs, precision, mode):
    """A few updates from the same weights on the same samples and noise give the same losses and
    weights as the update with no_grad targets, bit for bit, with clipping active (a small
    max_grad_norm)."""
    import sac_update

    city = grid_city(3, 3, seed=0)

    def run(reference: bool, max_grad_norm: float = 0.5) -> tuple[list[float], list[torch.Tensor]]:
        with monkeypatch.context() as m:
            if reference:
                _reference_update(m)
            torch.manual_seed(0)
            args = sac.Args(scenario="synthetic", hidden=16, batch_size=8, num_envs=num_envs, precision=precision, mode=mode, max_grad_norm=max_grad_norm, policy_out="")
            learner = sac.Learner(args, city, C.make_graph(city, args))
            buffer = sac_update.filled_replay(city.n_regions, 13, 32, seed=0)
            gen, losses = torch.Generator().manual_seed(0), []
            for i in range(4):
                torch.manual_seed(100 + i)  # the same reparameterisation noise in both runs
                out = learner.update(_with_local(buffer.sample(8, gen)) if mode == "decentralised" else buffer.sample(8, gen))
                losses += [float(out["loss/q"]), float(out["loss/policy"])]
            nets = (learner.actor, learner.critic, learner.critic_targ)
            return losses, [p.detach().clone() for net in nets for p in net.parameters()]

    (losses, weights), (ref_losses, ref_weights) = run(False), run(True)
    assert losses == ref_losses
    for w, r in zip(weights, ref_weights, strict=True):
        assert torch.equal(w, r)
    _, unclipped = run(False, max_grad_norm=1e6)  # the clipping did act: without it the weights differ
    assert any(not torch.allclose(w, u, rtol=1e-3, atol=1e-5) for w, u in zip(weights, unclipped, strict=True))
