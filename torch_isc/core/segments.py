"""Generic helpers over packed batches: reductions per segment (an item's rows), first
indices, a counter-based hash generator, and the small symmetric eigen-solve.

A *segment* index ``seg (N,)`` says which of ``n`` segments (items, triangles, ...) each row
belongs to; rows of one segment need not be contiguous unless said. Every helper is a few
tensor ops for the whole batch and keeps the dtype and device of its input.

Example:
    >>> x = torch.tensor([1.0, 2.0, 5.0, 3.0]); seg = torch.tensor([0, 0, 2, 2])
    >>> segment_sum(x, seg, 3).tolist(), segment_max(x, seg, 3).tolist()
    ([3.0, 0.0, 8.0], [2.0, -inf, 5.0])
    >>> first_index(torch.tensor([2, 0, 3])).tolist()
    [0, 2, 2]
"""
from __future__ import annotations

from typing import Iterator, Optional, Tuple

import torch

__all__ = ["edge_components", "segment_sum", "segment_max", "segment_min", "segment_count", "segment_mean", "segment_any",
           "segment_median", "first_index", "segment_rows", "local_index", "mix32", "hash_keys", "hash_to_unit", "hash_uniform",
           "sym2_eigvals", "sym2_eigvec", "expand_in_chunks"]


def segment_sum(x: torch.Tensor, seg: torch.Tensor, n: int) -> torch.Tensor:
    """``(n, ...)`` the sum of the rows ``x (N, ...)`` of each segment (0 where empty)."""
    return torch.zeros((n,) + tuple(x.shape[1:]), dtype=x.dtype, device=x.device).index_add_(0, seg, x)


def segment_max(x: torch.Tensor, seg: torch.Tensor, n: int, fill: Optional[float] = None) -> torch.Tensor:
    """``(n,)`` the largest ``x (N,)`` of each segment; ``fill`` where empty (default -inf, or
    the dtype's lowest value for integers). Also the start of a running maximum: a ``fill`` of
    0 gives ``max(0, ...)``."""
    if fill is None:
        fill = -float("inf") if x.dtype.is_floating_point else torch.iinfo(x.dtype).min
    return torch.full((n,), fill, dtype=x.dtype, device=x.device).scatter_reduce(0, seg, x, "amax")


def segment_min(x: torch.Tensor, seg: torch.Tensor, n: int, fill: Optional[float] = None) -> torch.Tensor:
    """``(n,)`` the smallest ``x (N,)`` of each segment; ``fill`` where empty (default inf)."""
    if fill is None:
        fill = float("inf") if x.dtype.is_floating_point else torch.iinfo(x.dtype).max
    return torch.full((n,), fill, dtype=x.dtype, device=x.device).scatter_reduce(0, seg, x, "amin")


def segment_count(seg: torch.Tensor, n: int) -> torch.Tensor:
    """``(n,)`` long, the rows of each segment (``seg`` in ``[0, n)``). A scatter-add, not
    ``bincount``: that one reads the largest index on the host (a synchronization on a GPU)."""
    return torch.zeros(n, dtype=torch.long, device=seg.device).index_add_(0, seg, torch.ones_like(seg, dtype=torch.long))


def segment_mean(x: torch.Tensor, seg: torch.Tensor, n: int) -> torch.Tensor:
    """``(n, ...)`` the mean of the rows of each segment (0 where empty)."""
    cnt = segment_count(seg, n).to(x.dtype).clamp_min(1)
    return segment_sum(x, seg, n) / cnt.view((n,) + (1,) * (x.dim() - 1))


def segment_any(mask: torch.Tensor, seg: torch.Tensor, n: int) -> torch.Tensor:
    """``(n,)`` bool, whether any row of the segment is True (no boolean indexing: no host read)."""
    return segment_max(mask.to(torch.int32), seg, n, fill=0) > 0


def segment_median(x: torch.Tensor, seg: torch.Tensor, n: int) -> torch.Tensor:
    """``(n,)`` the lower median of ``x`` within each segment (0 for empty segments)."""
    if x.numel() == 0:
        return torch.zeros(n, dtype=x.dtype, device=x.device)
    o1 = torch.argsort(x, stable=True)
    o2 = torch.argsort(seg[o1], stable=True)
    order = o1[o2]
    cnt = segment_count(seg, n)
    first = first_index(cnt)
    mid = (first + (cnt - 1).clamp_min(0) // 2).clamp_max(x.numel() - 1)
    return torch.where(cnt > 0, x[order][mid], torch.zeros(n, dtype=x.dtype, device=x.device))


def first_index(counts: torch.Tensor) -> torch.Tensor:
    """``(n,)`` the first row of each of ``n`` contiguous segments of ``counts (n,)`` rows."""
    return torch.cumsum(counts, 0) - counts


def segment_rows(first: torch.Tensor, counts: torch.Tensor, total: int) -> torch.Tensor:
    """``(total,)`` the rows ``first[k] .. first[k] + counts[k] - 1`` of the segments ``k``, one
    segment after another; ``total`` is ``counts.sum()``, known on the host (no host read here).

    Example:
        >>> segment_rows(torch.tensor([5, 0]), torch.tensor([2, 3]), 5).tolist()
        [5, 6, 0, 1, 2]
    """
    dev = counts.device
    seg = torch.repeat_interleave(torch.arange(counts.shape[0], device=dev), counts, output_size=total)
    return torch.arange(total, device=dev) + (first - first_index(counts))[seg]


def local_index(seg: torch.Tensor, first: torch.Tensor) -> torch.Tensor:
    """``(N,)`` each row's index within its contiguous segment (``first``: see :func:`first_index`)."""
    return torch.arange(seg.shape[0], device=seg.device) - first[seg]


# ------------------------------------------------------------------ counter-based random numbers
def mix32(x: torch.Tensor) -> torch.Tensor:
    """A 32-bit integer hash (lowbias32-like) in int64 arithmetic."""
    m = 0xFFFFFFFF
    x = x & m
    x = ((x >> 16) ^ x) * 0x7FEB352D & m
    x = ((x >> 15) ^ x) * 0x846CA68B & m
    x = (x >> 16) ^ x
    return x


def hash_keys(h: torch.Tensor, *keys: torch.Tensor) -> torch.Tensor:
    """Fold integer keys into the running hash ``h`` (so constant keys can be folded once)."""
    for k in keys:
        h = mix32(h * 0x9E3779B1 + k.long() + 0x632BE5AB)
    return h


def hash_to_unit(h: torch.Tensor, dtype) -> torch.Tensor:
    """Hashes ``h`` (32-bit values in int64) as uniform numbers in the open interval (0, 1)."""
    u = ((h.to(torch.float64) + 0.5) / 4294967296.0).to(dtype)
    # the cast can round the top values up to 1.0; keep the interval open
    return u.clamp_max(1.0 - torch.finfo(dtype).eps / 2)


def hash_uniform(*keys: torch.Tensor, dtype=torch.float32) -> torch.Tensor:
    """Uniform numbers in (0, 1) from integer keys: a counter-based generator, so an item's
    random stream depends only on its own keys (seed, local index, step), not on its batch."""
    return hash_to_unit(hash_keys(torch.zeros_like(keys[0], dtype=torch.long), *keys), dtype)


# ------------------------------------------------------------------ 2x2 symmetric eigen-solve
def sym2_eigvals(a: torch.Tensor, b: torch.Tensor, d: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """The eigenvalues ``(small, large)`` of the symmetric ``[[a, b], [b, d]]`` (elementwise),
    from the half difference of the diagonal: no cancellation of a squared trace."""
    half_diff = 0.5 * (a - d)
    rad = torch.sqrt(half_diff * half_diff + b * b)
    mid = 0.5 * (a + d)
    return mid - rad, mid + rad


def sym2_eigvec(a: torch.Tensor, b: torch.Tensor, d: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """``(n, 2)`` an eigenvector (not normalized) of the symmetric ``[[a, b], [b, d]]`` for its
    eigenvalue ``lam``: the better-conditioned (longer) of the two rows of the adjugate."""
    v1 = torch.stack([b, lam - a], 1)
    v2 = torch.stack([lam - d, b], 1)
    return torch.where((v1.norm(dim=1) >= v2.norm(dim=1))[:, None], v1, v2)


def expand_in_chunks(counts: torch.Tensor, budget: int) -> Iterator[Tuple[int, int, torch.Tensor, torch.Tensor]]:
    """Expand rows ``i`` into ``counts[i]`` candidate pairs, in consecutive row ranges
    ``[i0, i1)`` of at most ``budget`` pairs (at least one row each), so memory stays bounded.

    Yields ``(i0, i1, row, slot)``: for every pair of the range its row ``(M,)`` and its index
    ``(M,)`` among that row's candidates.

    Example:
        >>> [(a, b, r.tolist(), s.tolist()) for a, b, r, s in expand_in_chunks(torch.tensor([2, 0, 3]), 4)]
        [(0, 2, [0, 0], [0, 1]), (2, 3, [2, 2, 2], [0, 1, 2])]
    """
    dev = counts.device
    csum = torch.cumsum(counts, 0)
    P = counts.shape[0]
    i0, base = 0, 0
    while i0 < P:
        # the range's end and its last pair's running total in one host read (a range's sizes
        # are then known: no read in the expansion)
        i1 = torch.searchsorted(csum, base + budget, right=True).clamp(i0 + 1, P).view(1)
        i1, end = torch.cat([i1, csum.index_select(0, i1 - 1)]).tolist()
        n = counts[i0:i1]
        row = torch.repeat_interleave(torch.arange(i0, i1, device=dev), n, output_size=end - base)
        slot = torch.arange(end - base, device=dev) - (torch.cumsum(n, 0) - n)[row - i0]
        yield i0, i1, row, slot
        i0, base = i1, end


def edge_components(num_verts: int, edges: torch.Tensor, join: torch.Tensor) -> torch.Tensor:
    """``(V,)`` long: a label per vertex, the smallest vertex index of its component in the
    graph of the ``edges (E, 2)`` where ``join (E,)`` holds. Label propagation with root hooking
    and pointer jumping: each round every joined edge proposes the smaller label of its ends to
    both ends' labels (their roots), then two pointer jumps carry it to the ends; six launches a
    round. Convergence is read after rounds 4, 6, 8, 12, 16, 24, ... (a round after convergence
    changes nothing, and the fixed point, labels constant on each component and each the label
    of its smallest vertex, is the same whatever the rounds): in a 64-shape solve every mesh graph
    converged within 3 rounds (one host read a call) and the blob rule's neighbour graph of the
    points within 5, where propagation to the ends with one jump took 1-8 and 31 (403 rounds in
    all, counting each call's unchanged last one, against 601)."""
    with torch.no_grad():
        a = edges[:, 0]
        b = torch.where(join, edges[:, 1], a)              # an edge that does not join is a loop: no proposal
        flat = torch.stack([a, b], 1).reshape(-1)           # (gathers by index_select: faster than x[idx])
        lab = torch.arange(num_verts, device=edges.device)
        done, nxt = 0, 4
        while True:
            for _ in range(nxt - done):
                ends = lab.index_select(0, flat).view(-1, 2)   # (E, 2) the labels of both ends
                # (an elementwise minimum: a reduction over a dim of 2 is ~100x slower on a CPU)
                m = torch.minimum(ends[:, 0], ends[:, 1])
                # hook the ends' labels (the ends themselves follow them by the jumps)
                new = lab.scatter_reduce(0, ends[:, 0], m, "amin").scatter_reduce(0, ends[:, 1], m, "amin")
                new = new.index_select(0, new)             # pointer jumping, twice
                prev, lab = lab, new.index_select(0, new)
            if torch.equal(prev, lab):
                return lab
            done, nxt = nxt, nxt + (nxt // 2 if nxt & (nxt - 1) == 0 else nxt // 3)
