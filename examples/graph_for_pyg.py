"""The city as a torch-geometric graph: global (env.graph()) and from one agent's local view.

    python examples/graph_for_pyg.py
"""

import numpy as np
import torch
from torch_geometric.data import Data
from torch_geometric.nn import GCNConv

import marl_amod
from marl_amod.env.observations import split_local

env = marl_amod.parallel_env("synthetic")
obs, _ = env.reset(seed=0)

# Centralised: the whole graph, as torch-geometric expects it.
g = env.graph()  # x (N, 13) float32, edge_index (2, E) int64, edge_attr (E, 2) float32
data = Data(x=torch.from_numpy(g["x"]), edge_index=torch.from_numpy(g["edge_index"]),
            edge_attr=torch.from_numpy(g["edge_attr"]))
conv = GCNConv(data.num_node_features, 32)
h = conv(data.x, data.edge_index)
print(data, "->", tuple(h.shape))

# Decentralised: each agent rebuilds its own neighbourhood from its observation alone.
batch = torch.from_numpy(np.stack([obs[a] for a in env.agents]))  # (N, D)
own, context, neighbours, mask = split_local(batch)  # (N,13) (N,3) (N,K,13) (N,K)
lin = torch.nn.Linear(13, 32)
message = (lin(neighbours) * mask[..., None]).sum(1) / mask.sum(1, keepdim=True).clamp(min=1)
h_local = torch.relu(lin(own) + message)  # one mean-aggregation layer, shared parameters
print("local embeddings", tuple(h_local.shape))
