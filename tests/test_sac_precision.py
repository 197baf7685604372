"""SAC's opt-in bfloat16 update (``precision: bf16``), the shared end-of-episode book, the heap setting."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import yaml

from marl_amod.algos import common as C
from marl_amod.algos.sac import policy_sample
from marl_amod.errors import ConfigError
from marl_amod.models import TwinQ
from marl_amod.models.dense import DenseGraph
from marl_amod.models.gnn import GNNActor, StackedTwinQ
from marl_amod.scenario import grid_city


def _setup(hidden: int, batch: int = 64):
    city = grid_city(4, 4, seed=0)
    graph = DenseGraph(torch.tensor(city.edge_index), city.n_regions)
    torch.manual_seed(0)
    # features on the observations' scale (vehicle counts and demand up to a few tens)
    x = torch.rand(batch, city.n_regions, 13) * torch.linspace(1, 40, 13)
    y = torch.distributions.Dirichlet(torch.ones(batch, city.n_regions)).sample()
    return graph, x, y, StackedTwinQ(TwinQ(13, hidden, "gcn")), GNNActor(13, hidden, "gcn")


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.detach(), b.detach()
    return float((a - b).norm() / b.norm())


@pytest.mark.parametrize("hidden", [64, 256])
def test_bf16_critics_and_actor_agree_with_fp32_to_the_stated_tolerance(hidden):
    """Under the bf16 autocast the Q values, concentrations and gradients stay close to float32's
    (relative L2: Q and weight gradients 3%, concentrations 1%, dQ/dy 15%), and what the losses
    read (Q, concentrations) is float32."""
    graph, x, y, critic, actor = _setup(hidden)
    y.requires_grad_(True)
    amp = C.autocast("bf16")

    def run(ctx):
        critic.zero_grad()
        y.grad = None
        with ctx():
            q1, q2 = critic(x, graph, y)
            alpha = actor(x, graph)
        (q1.sum() + q2.sum()).backward()
        return q1, alpha, y.grad.clone(), [p.grad.clone() for p in critic.parameters()]

    (q, alpha, dy, grads), (qb, alphab, dyb, gradsb) = run(C.autocast("fp32")), run(amp)
    assert qb.dtype == alphab.dtype == torch.float32
    assert 0 < _rel(qb, q) < 0.03  # > 0: the matmuls did run in bfloat16
    assert _rel(alphab, alpha) < 0.01
    assert _rel(dyb, dy) < 0.15
    assert max(_rel(gb, g) for gb, g in zip(gradsb, grads, strict=True)) < 0.03
    assert all(g.dtype == torch.float32 for g in gradsb)  # float32 master weights get float32 gradients


def test_a_few_bf16_updates_reduce_the_critic_and_policy_losses():
    """Critic regression towards fixed targets and the policy loss against a fixed critic, both
    with their network passes under the bf16 autocast, fall within a few Adam steps."""
    graph, x, y, critic, actor = _setup(64)
    amp = C.autocast("bf16")
    target = torch.randn(x.shape[0])
    opt_c = torch.optim.Adam(critic.parameters(), lr=1e-2)
    losses = []
    for _ in range(30):
        with amp():
            q1, q2 = critic(x, graph, y)
        loss = ((q1 - target) ** 2).mean() + ((q2 - target) ** 2).mean()
        opt_c.zero_grad()
        loss.backward()
        opt_c.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]

    critic.requires_grad_(False)
    opt_a = torch.optim.Adam(actor.parameters(), lr=1e-2)
    gen_state = torch.get_rng_state()
    policy = []
    for _ in range(30):
        torch.set_rng_state(gen_state)  # the same reparameterisation noise every step
        y_pi, logp = policy_sample(actor, {"x": x}, "", graph, False, amp)
        with amp():
            q_pi = torch.min(*critic(x, graph, y_pi))
        loss_pi = (0.01 * logp - q_pi).mean()
        opt_a.zero_grad()
        loss_pi.backward()
        opt_a.step()
        policy.append(loss_pi.item())
    assert policy[-1] < policy[0] - 0.05 * abs(policy[0])


def test_bf16_runs_on_the_batched_path_and_is_refused_one_episode_at_a_time(tmp_path):
    from marl_amod.algos.registry import ALGOS, args_for

    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump({"name": "tiny", "source": "synthetic", "rows": 3, "cols": 3, "horizon": 6, "vehicles_per_region": 5}))
    with pytest.raises(ConfigError, match="num_envs"):
        args_for("sac", {"scenario": str(path), "precision": "bf16"})
    entry = ALGOS["sac"]
    args = entry.args(scenario=str(path), num_envs=4, precision="bf16", episodes=8, eval_every=4, eval_episodes=1, final_eval_episodes=1,
                      hidden=8, batch_size=8, warmup_steps=8, run_dir=str(tmp_path / "run"), policy_out=str(tmp_path / "p.pt"))
    card = entry.train(args)["card"]
    assert card["args"]["precision"] == "bf16" and card["episodes_trained"] == 8
    state = torch.load(tmp_path / "run" / "state.pt", map_location="cpu", weights_only=False)
    assert all(v.dtype == torch.float32 for v in state["critic"].values())  # master weights stay float32
    assert all(v.dtype == torch.float32 for v in state["actor"].values())


class _Best:
    """BestActor's interface, recording validations."""

    def __init__(self) -> None:
        self.calls, self.state = 0, {}

    def validate(self, actor, city, args) -> float:
        self.calls += 1
        return 1.0


def test_learner_update_marks_its_parts_in_order_and_moves_actor_critics_and_targets():
    """``Learner.update`` calls ``mark`` after each part, in the order benchmarks/sac_update.py
    reports them (so its table cannot silently lose a part), and one update changes the actor,
    the critics and, by Polyak averaging, the target critics."""
    import sac_update

    from marl_amod.algos.sac import Args, Learner

    city = grid_city(3, 3, seed=0)
    args = Args(scenario="synthetic", hidden=8, batch_size=4, num_envs=2, policy_out="")
    learner = Learner(args, city, C.make_graph(city, args))
    buffer = sac_update.filled_replay(city.n_regions, 13, 8, seed=0)
    nets = {"actor": learner.actor, "critic": learner.critic, "target": learner.critic_targ}
    before = {k: [p.detach().clone() for p in m.parameters()] for k, m in nets.items()}
    parts: list[str] = []
    learner.update(buffer.sample(4, torch.Generator().manual_seed(0)), parts.append)
    assert parts == sac_update.PARTS[:-1]  # all but the replay sample, which the caller takes
    for k, m in nets.items():
        assert any(not torch.equal(p, q) for p, q in zip(m.parameters(), before[k], strict=True)), k


def test_episode_book_validates_when_due_and_the_batch_that_runs_out_of_time(tmp_path):
    """Both trainers: a run stopped by its time limit before its first validation must not ship the untrained start."""
    from marl_amod.algos.a2c import Args

    args = Args(scenario="synthetic", episodes=100, eval_every=50, time_limit_s=1.0)
    saved, best = [], _Best()
    book = C.EpisodeBook(args, "a2c", torch.nn.Linear(1, 1), None, SimpleNamespace(env=None), C.Logger(tmp_path, tensorboard=False),
                         lambda: 5.0, best, lambda: saved.append(1) or (Path("s"), 0))
    stats = {"loss": 1.0}
    assert book.close(4, 4, stats) is True  # 5 s > the 1 s limit: stop
    assert best.calls == 1 and len(saved) == 1 and "eval/profit" in stats
    assert stats["time/wall_s"] == 5.0
    long = Args(scenario="synthetic", episodes=100, eval_every=50)
    book.args = long
    assert book.close(30, 4, {}) is False and best.calls == 1  # no limit, not due: no validation
    assert book.close(52, 4, {}) is False and best.calls == 2  # crossed episode 50: validated


def test_retained_heap_reuses_freed_activations_without_page_faults():
    """After ``retain_freed_memory`` a loop that allocates and frees megabyte tensors (an update's
    activations) runs without minor page faults (glibc only)."""
    code = textwrap.dedent(
        """
        import resource, torch
        from marl_amod.algos.common import retain_freed_memory
        if not retain_freed_memory():
            print("skip")
            raise SystemExit
        faults = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for i in range(20):
            if i == 10:
                f0 = faults()
            xs = [torch.ones(800_000) for _ in range(8)]  # 8 x 3.2 MB
            del xs
        print((faults() - f0) / 10)
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    if out == "skip":
        pytest.skip("not glibc")
    assert float(out) < 50  # without the threshold it is ~6,000 faults per round (one mapping per tensor)
