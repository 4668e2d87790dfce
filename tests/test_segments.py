"""Label propagation of core/segments.edge_components on graphs deeper than its first reads."""
import pytest
import torch

from torch_isc.core.segments import edge_components


def _union_find(n, edges, join):
    parent = list(range(n))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for (a, b), j in zip(edges.tolist(), join.tolist()):
        if j:
            ra, rb = root(a), root(b)
            parent[max(ra, rb)] = min(ra, rb)
    # the label is the smallest vertex of the component
    lab = [root(i) for i in range(n)]
    low = {}
    for i, r in enumerate(lab):
        low.setdefault(r, i)
    return [low[r] for r in lab]


@pytest.mark.parametrize("n, seed", [(1, 0), (7, 1), (300, 2), (2000, 3)])
def test_edge_components_on_long_random_paths(n, seed):
    """Paths through the vertices in random order (diameters up to 2000: many more rounds than
    the first convergence reads), cut at random edges: the labels of union-find."""
    g = torch.Generator().manual_seed(seed)
    order = torch.randperm(n, generator=g)
    e = torch.stack([order[:-1], order[1:]], 1)
    e = torch.stack([e.min(1).values, e.max(1).values], 1)
    join = torch.rand(e.shape[0], generator=g) > 0.02
    got = edge_components(n, e, join)
    assert got.tolist() == _union_find(n, e, join)
