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


@pytest.mark.parametrize("seed", range(4))
def test_edge_components_on_random_graphs(seed):
    """Random sparse graphs (many components, trees and cycles, repeated edges and loops, half
    the edges not joining): the labels of union-find."""
    g = torch.Generator().manual_seed(seed)
    n = int(torch.randint(1, 600, (1,), generator=g))
    e = torch.randint(0, n, (int(torch.randint(0, 2 * n, (1,), generator=g)), 2), generator=g)
    join = torch.rand(e.shape[0], generator=g) > 0.5
    assert edge_components(n, e, join).tolist() == _union_find(n, e, join)


def _chunks_by_loops(counts, budget):
    """expand_in_chunks by plain loops: greedy row ranges of at most ``budget`` pairs (a row
    alone when it has more), each row's pairs numbered 0..count-1."""
    out, i0, P = [], 0, len(counts)
    while i0 < P:
        i1, tot = i0 + 1, counts[i0]
        while i1 < P and tot + counts[i1] <= budget:
            tot += counts[i1]
            i1 += 1
        row = [i for i in range(i0, i1) for _ in range(counts[i])]
        slot = [j for i in range(i0, i1) for j in range(counts[i])]
        out.append((i0, i1, row, slot))
        i0 = i1
    return out


@pytest.mark.parametrize("seed", range(6))
def test_expand_in_chunks_against_loops(seed):
    """Random counts (zeros, rows larger than the budget) and budgets: the ranges, rows and
    slots of the plain loops, with one host read per range (gpu_floor's count, when present)."""
    from torch_isc.core.segments import expand_in_chunks
    g = torch.Generator().manual_seed(seed)
    P = int(torch.randint(1, 40, (1,), generator=g))
    counts = torch.randint(0, 9, (P,), generator=g) * (torch.rand(P, generator=g) > 0.3)
    budget = int(torch.randint(1, 30, (1,), generator=g))
    want = _chunks_by_loops(counts.tolist(), budget)
    got = [(a, b, r.tolist(), s.tolist()) for a, b, r, s in expand_in_chunks(counts, budget)]
    assert got == want
    from conftest import gpu_floor_counter
    OpCounter = gpu_floor_counter()
    if OpCounter is None:
        return
    with OpCounter(package="test_segments") as c:
        n = sum(1 for _ in expand_in_chunks(counts, budget))
    assert n == len(want) and c.syncs == n
