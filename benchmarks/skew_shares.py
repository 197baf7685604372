"""Busiest / average and median / average share of the requests out (place_table column 2) of each training
city at a few skew gammas, and of the held-out cities (gamma 1): the data the skew_gammas range is chosen from.

    python benchmarks/skew_shares.py
"""

from __future__ import annotations

import numpy as np

from marl_amod.algos import meta
from marl_amod.scenario.registry import load_city

GAMMAS = [1.0, 1.3, 1.6, 2.0, 2.5, 3.0]


def row(name: str) -> tuple[float, float]:
    """(busiest, median) share of the requests out of scenario ``name``, each x the average region's."""
    out = meta.place_table(load_city(name))[:, 2]
    return float(out.max()), float(np.median(out))


def main() -> None:
    print(f"{'city':24s} " + " ".join(f"{'g' + str(g):>12s}" for g in GAMMAS) + "   (busiest / median, x the average share)")
    for city in meta.TRAIN_CITIES:
        cells = [row(city if g == 1 else meta.skew_name(city, g)) for g in GAMMAS]
        print(f"{city:24s} " + " ".join(f"{b:5.2f}/{m:5.2f} " for b, m in cells))
    for city in meta.HELD_OUT:
        b, m = row(city)
        print(f"{city:24s} {b:5.2f}/{m:5.2f}  (held out, as it is)")


if __name__ == "__main__":
    main()
