"""Policy and value networks: GNN (the paper's), local shared-parameter actor, MLP and CNN ablations."""

from marl_amod.models.cnn import CNNActor
from marl_amod.models.distributions import dirichlet, dirichlet_log_prob_from_gammas, dirichlet_mean, gamma, gamma_log_prob
from marl_amod.models.gnn import (
    READOUTS,
    FleetReadout,
    GNNActor,
    GNNQCritic,
    GNNValueCritic,
    RegionIdentity,
    TwinQ,
    batch_edge_index,
)
from marl_amod.models.local import LocalActor, LocalValueCritic
from marl_amod.models.mlp import MLPActor

ACTORS = {"gnn": GNNActor, "local": LocalActor, "mlp": MLPActor, "cnn": CNNActor}


def build_actor(
    kind: str, city, n_features: int = 13, hidden: int = 32, conv: str = "gcn", readout: str = "none", agent_id: bool = False,
    standardise: bool = False,
):
    """An actor by name for ``city``; MLP and CNN are tied to the city's size/grid, GNNs are not
    (unless ``agent_id``). ``readout`` and ``agent_id`` (a one-hot region identity on every
    node's input, sized for ``city``) are GNN options: the others see the whole fleet, each
    region in its place, already (MLP, CNN), or only a neighbourhood by design (local).
    ``standardise`` (per-input statistics carried in the weights) is an MLP option."""
    for name, on in (("readout", readout != "none"), ("agent_id", agent_id)):
        if on and kind != "gnn":
            raise ValueError(f"{name} is a GNN actor option; a {kind} actor has none")
    if standardise and kind != "mlp":
        raise ValueError(f"standardise is an MLP actor option; a {kind} actor has none")
    if kind == "gnn":
        return GNNActor(n_features, hidden, conv, readout, city.n_regions if agent_id else 0)  # type: ignore[arg-type]
    if kind == "local":
        return LocalActor(n_features, hidden)
    if kind == "mlp":
        return MLPActor(n_features, hidden, city.n_regions, standardise)
    if kind == "cnn":
        from marl_amod.models.cnn import grid_layout

        rows, cols, cells = grid_layout(city.positions)
        return CNNActor(n_features, hidden, rows, cols, cells.tolist())
    raise ValueError(f"unknown actor {kind!r}; known: {', '.join(ACTORS)}")

__all__ = [
    "ACTORS", "READOUTS", "FleetReadout", "RegionIdentity", "TwinQ", "build_actor", "CNNActor", "GNNActor", "GNNQCritic", "GNNValueCritic", "LocalActor", "LocalValueCritic", "MLPActor",
    "batch_edge_index", "dirichlet", "dirichlet_log_prob_from_gammas", "dirichlet_mean", "gamma", "gamma_log_prob",
]
