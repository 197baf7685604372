"""Seconds per meta-imitation update: the update's cities one after another or padded into one batch, the heads split or not.

An update of ``configs/meta/bc_dagger_all.yaml`` draws ``cities_per_update`` training cities and
``num_envs`` trials of ``trial_episodes`` demonstration episodes of each, as the run does (its
demonstrations, ``runs/meta_demos`` by default, with the structure and place columns), and times
the loss, its backward pass, the clipping and the Adam step, three ways in one process on the same
draws, alternating, so the machine's load hits all alike (the ratios are what to read):

* ``per city``: :func:`~marl_amod.algos.meta_imitation.cities_losses` with ``batch="apart"``:
  :func:`~marl_amod.algos.meta_imitation.imitation_losses` once per city, averaged (the path
  before the padded batch; ``pad_cities: false``);
* ``padded``: ``batch="padded"``, one padded batch (``pad_cities: true``, ``pack_cities: false``: the shipped recipes);
* ``packed``: ``batch="packed"``, the cities side by side in one batch, no padding (``pack_cities: true``, the default);
* ``padded, heads on the concatenation``: the same, with the model's heads run on the readout's
  full output (:func:`~marl_amod.models.recurrent.concatenated_heads`, the fleet summary copied to
  every region) instead of split (the model's own ``_heads``: the summary's columns once per graph);
* ``padded, bf16``: the padded form under bf16 autocast (a meta config's ``precision: bf16``): pays on a
  CPU with AMX or AVX512-BF16 (this one: ``torch.backends.cpu.get_cpu_capability()`` is printed);
* ``padded, bf16, memory cast per reader``: the same with the GRU memory handed to the layers after the GRU
  in float32, so each product casts it again (the model before :func:`~marl_amod.models.recurrent._for_products`);
* ``packed, bf16``: the packed form under bf16 autocast.

It also prints the largest difference of the float32 losses over the timed updates (float rounding), the
largest relative difference of the bf16 loss to them, and the largest difference between the two padded bf16 forms (0:
the products see the same values).

    python benchmarks/meta_update.py [--config configs/meta/bc_dagger_l1.yaml] [--updates 20] [--hidden 64 128] [--num-envs 16 4] [--threads 2]

Every row of the table is one (hidden units, trials per city) setting; the config's by default.
"""

from __future__ import annotations

import argparse
import itertools
import os
import time
from collections.abc import Callable
from typing import NamedTuple

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from marl_amod.algos import common as C  # noqa: E402
from marl_amod.algos import meta  # noqa: E402
from marl_amod.algos import meta_imitation as mi  # noqa: E402
from marl_amod.algos.registry import ALGOS  # noqa: E402
from marl_amod.config import load_config  # noqa: E402
from marl_amod.models import recurrent  # noqa: E402
from marl_amod.scenario import load_city  # noqa: E402

SPLIT_HEADS = recurrent._heads
CAST_ONCE = recurrent._for_products


def per_reader(memory: torch.Tensor) -> torch.Tensor:
    """The float32 memory itself: every product after the GRU casts it under autocast."""
    return memory


class Form(NamedTuple):
    batch: mi.CitiesBatch
    heads: Callable
    precision: C.Precision
    memory_read: Callable = CAST_ONCE


FORMS = {"per city": Form("apart", SPLIT_HEADS, "fp32"), "padded": Form("padded", SPLIT_HEADS, "fp32"),
         "packed": Form("packed", SPLIT_HEADS, "fp32"),
         "padded, heads on the concatenation": Form("padded", recurrent.concatenated_heads, "fp32"),
         "padded, bf16": Form("padded", SPLIT_HEADS, "bf16"), "padded, bf16, memory cast per reader": Form("padded", SPLIT_HEADS, "bf16", per_reader),
         "packed, bf16": Form("packed", SPLIT_HEADS, "bf16")}


def timed_update(form: str, model: meta.RecurrentGNN, opt: torch.optim.Optimizer, draws: list, args: mi.Args) -> tuple[float, float]:
    """(seconds, loss) of one whole update as training does it, in one of the ``FORMS``."""
    chosen = FORMS[form]
    recurrent._heads, recurrent._for_products = chosen.heads, chosen.memory_read
    start = time.perf_counter()
    with C.autocast(chosen.precision)():
        ce, vl = mi.cities_losses(model, draws, args.gamma, chosen.batch, args.fit)
    loss = ce + args.value_coef * vl
    opt.zero_grad()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), args.max_grad_norm)
    opt.step()
    return time.perf_counter() - start, loss.item()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default="configs/meta/bc_dagger_all.yaml")
    p.add_argument("--updates", type=int, default=20, help="timed updates per path (after 2 warm-up ones each)")
    p.add_argument("--hidden", type=int, nargs="+", default=None, help="hidden units to compare (default: the config's)")
    p.add_argument("--num-envs", type=int, nargs="+", default=None, help="trials per city to compare (default: the config's)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (a meta config's threads: one run alone may use both cores)")
    opts = p.parse_args()
    if opts.threads < 1:
        p.error(f"--threads {opts.threads}: at least one thread")
    _, args = load_config(opts.config, {k: v.args for k, v in ALGOS.items()})
    torch.set_num_threads(opts.threads)
    cities = {name: load_city(name) for name in args.cities}
    data = mi.load_all(args, cities)
    print(f"{opts.config}: {args.cities_per_update} cities x {args.num_envs} trials x {args.trial_episodes} episodes per update, "
          f"regions {sorted(c.n_regions for c in cities.values())}, {torch.get_num_threads()} torch thread(s), CPU capability {torch.backends.cpu.get_cpu_capability()}")  # fmt: skip
    print("| hidden | trials per city | " + " | ".join(f"{form} (s/update)" for form in FORMS) + " | padded vs per city | packed vs padded "
          "| split heads vs concatenation | bf16 vs float32 | memory cast once vs per reader | packed vs padded, bf16 | max loss difference "
          "| bf16's max relative loss difference | max difference of the padded bf16 forms |")  # fmt: skip
    print("|---" * (len(FORMS) + 11) + "|")
    for hidden, num_envs in itertools.product(opts.hidden or [args.hidden], opts.num_envs or [args.num_envs]):
        run = args.model_copy(update={"hidden": hidden, "num_envs": num_envs})
        torch.manual_seed(0)
        model = meta.make_model(run)
        opt = torch.optim.Adam(model.parameters(), lr=0.0)  # lr 0: every form sees the same weights every update
        rng = np.random.default_rng(0)
        times: dict[str, list[float]] = {form: [] for form in FORMS}
        diff = bf16_diff = cast_diff = 0.0
        for i in range(opts.updates + 2):
            draws = []
            for _ in range(run.cities_per_update):
                demos, graph = data[run.cities[int(rng.integers(len(run.cities)))]]
                draws.append((demos, mi.draw_trials(demos, run, rng), graph))
            timed = {form: timed_update(form, model, opt, draws, run) for form in FORMS}
            if i >= 2:
                for form, (seconds, _) in timed.items():
                    times[form].append(seconds)
                losses = [loss for form, (_, loss) in timed.items() if FORMS[form].precision == "fp32"]
                diff = max(diff, max(losses) - min(losses))
                bf16_diff = max(bf16_diff, abs(timed["padded, bf16"][1] / timed["padded"][1] - 1))
                cast_diff = max(cast_diff, abs(timed["padded, bf16"][1] - timed["padded, bf16, memory cast per reader"][1]))
        t = {form: float(np.median(times[form])) for form in FORMS}
        print(f"| {hidden} | {num_envs} | " + " | ".join(f"{t[form]:.3f}" for form in FORMS)
              + f" | {t['per city'] / t['padded']:.2f}x | {t['padded'] / t['packed']:.2f}x | {t['padded, heads on the concatenation'] / t['padded']:.2f}x "
              f"| {t['padded'] / t['padded, bf16']:.2f}x | {t['padded, bf16, memory cast per reader'] / t['padded, bf16']:.3f}x "
              f"| {t['padded, bf16'] / t['packed, bf16']:.2f}x | {diff:.1e} | {bf16_diff:.1e} | {cast_diff:.1e} |", flush=True)  # fmt: skip
    recurrent._heads, recurrent._for_products = SPLIT_HEADS, CAST_ONCE


if __name__ == "__main__":
    main()
