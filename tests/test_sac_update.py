"""SAC's per-transition update: the faster forms compute what the plain PyTorch forms do.

``Learner.update`` clips with :func:`~marl_amod.algos.sac.clip_grad_norm` (one concatenated norm
instead of ``clip_grad_norm_``'s per-tensor norms) and runs the target side in inference mode;
both must leave the update's numbers as they were, to float rounding.
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path

import pytest
import torch

from marl_amod.algos import common as C
from marl_amod.algos import sac
from marl_amod.scenario import grid_city


@pytest.mark.parametrize("max_norm", [1e-3, 1e3])  # clipping active / inactive
def test_clip_grad_norm_scales_gradients_as_torch_clip_grad_norm(max_norm):
    torch.manual_seed(0)
    ours, ref = [torch.nn.Parameter(torch.zeros(s)) for s in [(3, 4), (4,), (2, 5, 5)]], [torch.nn.Parameter(torch.zeros(s)) for s in [(3, 4), (4,), (2, 5, 5)]]
    for p, q in zip(ours, ref, strict=True):
        p.grad = torch.randn(p.shape) * 10
        q.grad = p.grad.clone()
    ours[1].grad = ref[1].grad = None  # a parameter without a gradient is skipped
    before = [p.grad.clone() if p.grad is not None else None for p in ours]
    sac.clip_grad_norm(ours, max_norm)
    torch.nn.utils.clip_grad_norm_(ref, max_norm)
    for p, q, b in zip(ours, ref, before, strict=True):
        if b is None:
            assert p.grad is None
            continue
        torch.testing.assert_close(p.grad, q.grad, rtol=1e-6, atol=0)
        assert torch.equal(p.grad, b) == (max_norm == 1e3)  # scaled only when the norm exceeds the bound


def _reference_update(monkeypatch: pytest.MonkeyPatch) -> None:
    """The update as it was: torch's clip_grad_norm_ and no_grad for the target side."""
    monkeypatch.setattr(sac, "clip_grad_norm", lambda params, max_norm: torch.nn.utils.clip_grad_norm_(params, max_norm, foreach=True))
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
    weights as the update with torch's clipping and no_grad targets (float rounding), with
    clipping active (a small max_grad_norm)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
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
    assert losses == pytest.approx(ref_losses, rel=1e-4)
    for w, r in zip(weights, ref_weights, strict=True):
        torch.testing.assert_close(w, r, rtol=1e-4, atol=1e-6)
    _, unclipped = run(False, max_grad_norm=1e6)  # the clipping did act: without it the weights differ
    assert any(not torch.allclose(w, u, rtol=1e-3, atol=1e-5) for w, u in zip(weights, unclipped, strict=True))
