"""EstimateTopology (Section 3.2): the vertex signs, from the Ising model of the line
evidence (edge weights of eq. 3.6, simulated annealing), or from an inside/outside oracle.

Dimension-free: the edge weights read the line fits through the mesh's kernel, and the
Ising model, the colouring and the annealer work on any simplicial mesh's edge list.
"""
from __future__ import annotations

import functools
import math

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Optional, Protocol, Sequence, Union

import torch

from torch_isc._helpers import one_line

from torch_isc.core.mesh import MeshBatch
from torch_isc.core.points import PointSetError
from torch_isc.core.segments import edge_components, first_index, hash_keys, hash_to_unit, mix32, segment_count, segment_max, segment_min
from torch_isc.pipeline.knobs import check_section, knob
from torch_isc.pipeline import budget, graphs

if TYPE_CHECKING:
    from torch_isc.pipeline.evidence import Evidence, EvidenceConfig
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["TopologyConfig", "edge_weights", "vertex_coloring", "anneal", "ising_energy", "sign_islands",
           "remove_small_islands", "SignSource", "IsingSigns", "OracleSigns", "SignOracleError"]


@dataclass
class TopologyConfig:
    """The Ising estimate of the signs (flat keys of configs/default.yaml)."""
    #: confidence of an empty triangle, L = (1, 1, 1): "no curve crosses here"
    empty_weight: float = knob(1.0, ge=0)
    anneal_sweeps: int = knob(120, gt=0)
    anneal_t_start: float = knob(3.0, gt=0)
    anneal_t_end: float = knob(0.02, gt=0)
    #: start temperature at finer levels, warm-started from the previous signs
    anneal_warm_t_start: float = knob(0.3, gt=0)
    anneal_replicas: int = knob(4, gt=0)
    #: zero-temperature sweeps after the schedule
    anneal_greedy_sweeps: int = knob(4, ge=0)
    #: sign regions of fewer vertices (and no boundary vertex) are flipped; 0 or 1 disables
    min_island_vertices: int = knob(2, ge=0)
    #: coupling toward equal signs on an edge provably farther from the data than the tolerance
    #: allows (pipeline/support.py); 0 disables (the default: measured +1 of 192 on the broad
    #: suite beside the cluster moves, but it opened a loop inside a figure of data/family)
    unsupported_weight: float = knob(0.0, ge=0)
    #: ...the distance it starts at, in noise widths (never below the tolerance); the cluster
    #: moves' far vertices are those beyond it
    unsupported_noise_widths: float = knob(3.0, ge=0)
    #: rounds of cluster moves after annealing (pipeline/simplify.py); 0 disables
    cluster_rounds: int = knob(2, ge=0)
    #: opening of the signs at this many noise widths, or this many tolerances where that is more
    #: (pipeline/simplify.py: open_stage); both 0 disables
    open_noise_widths: float = knob(0.0, ge=0)
    open_tolerances: float = knob(4.0, ge=0)
    #: ...its distance rounds along edges, and whether only whole sign regions flip
    open_rounds: int = knob(16, ge=1)
    open_whole_regions: bool = knob(True)
    #: ...and whether such a region first joins a neighbour of its sign across one vertex
    open_merge: bool = knob(True)
    #: ...but a region its own data surround (a small closed curve) is kept
    open_keep_surrounded: bool = knob(True)
    #: a vertex that a ring of points with no curve near encloses (consecutive chords at
    #: most this many times its distance to them), with no curve in its star, takes the other
    #: sign (a missed small closed curve; pipeline/simplify.py: enclose_stage); 0 disables (the
    #: default: 1.8 found satellites, +3/+3/+2 of 192 on the broad suite's seeds 0/1/2, but lost
    #: an annulus at 1% noise on the default sample, 413 -> 412 of 440)
    enclose_chord: float = knob(1.8, ge=0, le=2)
    #: ...when no point of its star is nearer than this many noise widths
    enclose_noise_widths: float = knob(2.0, ge=0)
    #: ...seeing the points of the triangles with a corner at most this many edges away
    enclose_rings: int = knob(2, ge=0)
    #: ...and at least this many points in the ring (a few scattered outliers are no curve)
    enclose_min_points: int = knob(6, ge=3)
    #: small isolated clusters of points (pipeline/blobs.py): a connected component of the
    #: graph of each point's blob_neighbours nearest neighbours with blob_min_points to
    #: blob_max_points points gets a vertex at its centroid, which takes the other sign when no
    #: curve explains the cluster (a small closed curve of a few samples); 0 disables
    blob_min_points: int = knob(6, ge=0)
    blob_max_points: int = knob(16, ge=1)
    blob_neighbours: int = knob(3, ge=1)
    #: strength of the winding-number prior (pipeline/winding.py), a field term in the Ising
    #: energy; 0 disables (signs bit-identical to without it)
    winding_weight: float = knob(0.0, ge=0)
    #: neighbours of each point in its normal fit and the orientation graph
    winding_neighbours: int = knob(12, ge=3)
    #: power iterations of the orientation's Z2 synchronisation
    winding_sync_iterations: int = knob(30, ge=0)
    #: the winding number's smoothing length, in noise widths (or sample spacings, the larger)
    winding_smoothing: float = knob(2.0, gt=0)
    #: rounds of the tangent-notch rule (pipeline/notches.py): a vertex whose neighbours along
    #: the data's direction, on both sides, all have the other sign takes theirs; 0 disables
    notch_rounds: int = knob(1, ge=0)
    #: ...where the tangents of its star's points agree at least this much ((l1 - l2)/(l1 + l2))
    notch_coherence: float = knob(0.6, ge=0, le=1)
    #: ...its neighbours within this many degrees of that direction
    notch_cone: float = knob(35.0, gt=0, lt=90)
    #: ...and its star holds at least this many points
    notch_min_points: int = knob(3, ge=1)
    #: channel filling (pipeline/channels.py): a vertex whose walks along the data's direction,
    #: over its own sign, reach the other sign both ways within this many noise widths in all
    #: takes that sign (a stroke cut or two curves bridged by a short run across the data); off
    #: by default: broad suite 1% noise 28/25/29 -> 29/24/30 of 48 on seeds 0/1/2, totals
    #: 125/122/125 -> 127/121/125 of 192 (a filled vertex beside a serif's wall opened a loop)
    channel_fill: bool = knob(False)
    channel_noise_widths: float = knob(15.0, ge=0)
    #: ...or this many tolerances, where that is longer
    channel_tolerances: float = knob(0.0, ge=0)
    #: ...where the star's tangents agree at least this much ((l1 - l2)/(l1 + l2))
    channel_coherence: float = knob(0.6, ge=0, le=1)
    #: ...its star holds at least this many points
    channel_min_points: int = knob(3, ge=1)
    #: ...each step within this many degrees of the walking vertex's direction
    channel_cone: float = knob(55.0, gt=0, lt=90)
    #: ...and at most this many steps each way
    channel_rounds: int = knob(8, ge=1)
    #: ...and whether runs of the inside sign (bridges) are cut too, after the cuts are filled
    channel_bridges: bool = knob(False)
    #: weight of the crust parity coupling (pipeline/crust.py): an edge crossing the samples'
    #: nearest-neighbour crust an odd number of times couples its ends to opposite signs, an
    #: even (nonzero) number to equal signs; only on clean items; 0 disables (2: broad suite
    #: noise-free 44/41/43 -> 46/43/45 of 48 on seeds 0/1/2, noisy levels unchanged)
    crust_weight: float = knob(2.0, ge=0)
    #: ...items whose estimated noise is at most this many tolerances
    crust_noise_tolerances: float = knob(10.0, ge=0)
    #: ...and at most this many median sample spacings
    crust_noise_spacings: float = knob(0.3, ge=0)
    #: ...segments at most this many median sample spacings long
    crust_max_length: float = knob(3.0, gt=0)
    #: split the triangles with an edge the crust says the mesh gets wrong (its signs contradict
    #: the crust's parity, or it crosses both walls of a gap), while their longest edge is above
    #: this many sample spacings (:func:`~torch_isc.pipeline.crust.crust_contradictions`); 0 disables
    crust_refine: float = knob(1.0, ge=0, le=100)
    #: weight of the crust's sides as a field on every vertex, on the items whose crust is
    #: closed (:func:`~torch_isc.pipeline.crust.crust_sides`): the even-odd rule says which
    #: side each vertex is on, so nested curves a few spacings apart keep their alternation where
    #: the couplings only fix it edge by edge; 0 disables
    crust_sides: float = knob(2.0, ge=0)

    def __post_init__(self):
        check_section(self)


def edge_weights(mesh: MeshBatch, L: torch.Tensor, eps: torch.Tensor, count: torch.Tensor,
                 min_points: int, empty_weight: float, pooled_count: Optional[torch.Tensor] = None,
                 reach: Optional[torch.Tensor] = None, noise2: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Edge weights ``H_e`` of eq. 3.6 (``(E,)``).

    Triangles whose fit rests on ``min_points`` or more points contribute
    ``w_t = (ε_max−ε_t)/(ε_max−ε_min)`` (extremes per item). A fit on fewer points is not
    meaningful: such a triangle gives no evidence, unless it is empty, in which case it
    contributes ``L = (1,1,1)`` with ``empty_weight``. With ``pooled_count`` (the points
    behind pooled fits, see :func:`pooled_moments`), ``L, eps`` are the pooled fits and a
    triangle counts as empty only when its neighbourhood is empty too. ``reach`` ``(T, 3)``
    (see :func:`crossing_reach`) drops the crossing evidence of edge ``k`` where the line
    crosses it outside the extent of its points.
    """
    dt = L.dtype
    B = mesh.num_items
    support = count if pooled_count is None else pooled_count
    fit = support >= min_points
    empty = (count == 0) & ~fit
    fi = mesh.face_item
    big = torch.finfo(dt).max
    # the triangles without a fit enter the extremes as the fills (masks: no host read)
    emax = segment_max(torch.where(fit, eps, -big), fi, B, fill=-big)
    emin = segment_min(torch.where(fit, eps, big), fi, B, fill=big)
    if noise2 is not None:
        # fits within the noise are all equally good: dense noisy data would otherwise spread
        # tiny differences of near-noise errors over the whole range [0, 1]
        emin = torch.maximum(emin, noise2.to(dt))
    span = (emax - emin)[fi]
    w = torch.where(span > 0, (emax[fi] - eps) / span.clamp_min(torch.finfo(dt).tiny), torch.ones_like(eps)).clamp(0, 1)
    w = torch.where(fit, w, torch.zeros_like(w))
    w = torch.where(empty, torch.full_like(w, float(empty_weight)), w)
    sig = torch.where(empty[:, None], torch.ones_like(L), torch.where(L >= 0, 1.0, -1.0).to(dt))
    ea, eb = mesh.kernel.edge_corners
    prod = sig[:, ea] * sig[:, eb]
    if reach is not None:
        # a line testifies to a crossing only where its points are, not where it is extrapolated
        prod = torch.where((prod < 0) & ~reach, torch.zeros_like(prod), prod)
    H = torch.zeros(mesh.edges.shape[0], dtype=dt, device=L.device)
    H.index_add_(0, mesh.face_edges.reshape(-1), (-prod * w[:, None]).reshape(-1))
    return H


# ------------------------------------------------------------------- Ising model
_COLOR_ROUNDS = 16          # colouring rounds run before the first host read (chains are ~12 deep)


class _Coloring:
    """Greedy colouring in order of hashed priorities, as a fixed point: a vertex's colour is the
    smallest one that none of its higher-priority active neighbours has. Iterating that rule from
    any start fixes every vertex once its higher-priority neighbours are fixed (Jones–Plassmann's
    rounds), so a block of rounds runs without a host read and one read says whether the last
    round changed anything."""

    def __init__(self, mesh: MeshBatch, active: Optional[torch.Tensor], max_colors: int):
        V = mesh.verts.shape[0]
        dev = mesh.device
        local = torch.arange(V, device=dev) - mesh.verts_first_idx[mesh.vert_item]
        prio = mix32(local * 2654435761 + 12345) * V + local        # unique within an item
        act = torch.ones(V, dtype=torch.bool, device=dev) if active is None else active
        e = mesh.edges
        src = torch.cat([e[:, 0], e[:, 1]])
        dst = torch.cat([e[:, 1], e[:, 0]])
        before = act[src] & act[dst] & (prio[src] > prio[dst])    # src is coloured before dst
        self.C = int(max_colors) + 2                                # colours 0..max_colors, a dump column
        self.src = torch.where(before, src, V)                      # slot V reads the dump column
        self.flat = dst * self.C
        self.ones = torch.ones(src.shape[0], dtype=torch.int8, device=dev)
        self.color = torch.zeros(V + 1, dtype=torch.long, device=dev)
        self.color[V:] = self.C - 1
        self.V, self.active = V, act

    def run(self, rounds: int) -> torch.Tensor:
        """``rounds`` more rounds; returns a 0-dim bool, whether the last one changed a colour."""
        V, C = self.V, self.C
        changed = torch.zeros((), dtype=torch.bool, device=self.color.device)
        for r in range(rounds):
            used = torch.zeros(V * C, dtype=torch.int8, device=self.color.device)
            used.scatter_(0, self.flat + self.color[self.src], self.ones)
            new = torch.argmin(used.view(V, C)[:, :C - 1], 1)     # first colour not used
            if r == rounds - 1:
                changed = (new != self.color[:V]).any()
            self.color[:V] = new
        return changed

    def result(self) -> torch.Tensor:
        return torch.where(self.active, self.color[:self.V], -1)


def vertex_coloring(mesh: MeshBatch, active: Optional[torch.Tensor] = None, max_colors: int = 64) -> torch.Tensor:
    """Greedy colouring (Jones–Plassmann with hashed priorities): adjacent vertices get
    different colours; ``-1`` for inactive vertices. Depends only on each item's own mesh.
    Rounds run in blocks of 16 between host reads (one read for usual meshes)."""
    with torch.no_grad():
        col = _Coloring(mesh, active, max_colors)
        while bool(col.run(_COLOR_ROUNDS)):
            pass
        return col.result()


def _coupling_table(mesh: MeshBatch, H: torch.Tensor, rows: torch.Tensor, pos: torch.Tensor, D: int, pad: int):
    """Padded neighbour table of the vertices ``rows (n,)``: ``(D, n)`` neighbour slots (as
    ``pos`` of the neighbour; ``pad`` in unused slots, a zero column of the state) and
    ``(D, n)`` couplings ``H_e`` (0 in unused slots), neighbours ascending as in the CSR
    adjacency, so that a sum over the slots adds the same terms in the same order."""
    first, nbrs = mesh.vert_neighbors
    V = mesh.verts.shape[0]
    E = mesh.edges.shape[0]
    slot = torch.arange(D, device=H.device)[:, None]
    start = first[rows][None, :]
    valid = slot < (first[rows + 1] - first[rows])[None, :]
    nb = torch.cat([nbrs, nbrs.new_zeros(1)])[torch.where(valid, start + slot, nbrs.shape[0])]
    lo, hi = torch.minimum(rows[None, :], nb), torch.maximum(rows[None, :], nb)
    eid = torch.searchsorted(mesh.edges[:, 0] * V + mesh.edges[:, 1], lo * V + hi).clamp_max(max(E - 1, 0))
    Hx = torch.cat([H, H.new_zeros(1)])
    w = torch.where(valid, Hx[torch.where(valid, eid, E)], torch.zeros((), dtype=H.dtype, device=H.device))
    return torch.where(valid, pos[nb], pad), w


#: a sum over the slot axis of at most this many slots adds them in order on the CPU, the order
#: of the CSR product this replaced, so the signs are bit-identical to it (torch's CPU sum runs
#: 16-row cascades, and in order only over whole blocks of 4 vector registers of outputs: tables
#: are padded to whole blocks of _BLOCK rows, 64 floats = 4 AVX-512 registers). A wider table
#: is summed in chunks, each chunk's sum written into a carry slot that opens the next chunk.
#: tests/test_fit.py checks the order bit for bit.
_ORDERED_SLOTS = 17
_BLOCK = 64
#: most vertices have at most this many neighbours: they get a narrow table, the rest a full one
_NARROW = 8
#: the local fields of a sweep as one embedding bag (1 launch) instead of a gather, a product and
#: a sum per part (3-4 launches; 5-7 colour classes x 124 sweeps a level), per device type (the
#: rest: True). Same bits either way; on a CPU the bag ran about 1.2x slower (64 shapes: 3.0 s
#: against 2.5 s an anneal call), so the CPU keeps the gathers
_FIELDS_BY_BAG = {"cpu": False}


class _ColorClass:
    """One colour class of the annealer's state ``s (R, columns)``: its columns ``a:a+width``,
    its padded neighbour tables as one flat gather ``idx (R·L,)`` of the flattened state with
    couplings ``w (L,)``, in parts (the narrow and the full table: ``(start, D, rows, column)``),
    and buffers and views made once, so that a sweep is a fixed sequence of ops writing in place."""

    def __init__(self, s: torch.Tensor, a: int, width: int, idx: torch.Tensor, w: torch.Tensor, parts):
        R = s.shape[0]
        self.a, self.width, self.idx, self.w = a, width, idx, w
        self.flat = s.view(-1)
        self.sg = s[:, a:a + width]
        self.f = torch.empty(R, width, dtype=s.dtype, device=s.device)
        self.x = torch.empty_like(self.f)
        self.zero = torch.zeros((), dtype=s.dtype, device=s.device)
        self.one = torch.ones((), dtype=s.dtype, device=s.device)
        self.by_bag = _FIELDS_BY_BAG.get(s.device.type, True)
        if self.by_bag:
            self._bags(R, idx, w, parts)
            return
        self.p = torch.empty(idx.shape[0], dtype=s.dtype, device=s.device)
        pv = self.p.view(R, -1)
        self.sums = []                                  # (slots, out): in order, chunk by chunk
        for a0, D, m, c0 in parts:
            t = pv[:, a0:a0 + D * m].view(R, D, m)
            for lo in range(0, D, _ORDERED_SLOTS):
                hi = lo + _ORDERED_SLOTS
                self.sums.append((t[:, lo:hi], t[:, hi] if hi < D else self.f[:, c0:c0 + m]))

    def _bags(self, R: int, idx: torch.Tensor, w: torch.Tensor, parts) -> None:
        """The same tables as bags, one per (replica, column), slots in order: an embedding bag
        sums a bag's weighted entries in order, so one op gives the fields bit for bit (the
        products ``H_ij F_j`` are exact, ``F_j`` = ±1 or the zero column; a carry slot adds +0)."""
        s = self.sg
        iv = idx.view(R, -1)
        bi, bw, bs = [], [], []
        for a0, D, m, c0 in parts:
            bi.append(iv[:, a0:a0 + D * m].view(R, D, m).transpose(1, 2).reshape(R, -1))
            bw.append(w[a0:a0 + D * m].view(D, m).T.reshape(-1))
            bs.append(torch.full((m,), D, dtype=torch.long, device=s.device))
        self.bag_idx = torch.cat(bi, 1).reshape(-1)
        self.bag_w = torch.cat(bw).repeat(R)
        sizes = torch.cat(bs).repeat(R)
        self.bag_off = torch.cumsum(sizes, 0) - sizes
        self.table = self.flat.view(-1, 1)

    def fields(self) -> torch.Tensor:
        """``(R, width)`` local fields ``Σ_j H_ij F_j``: one embedding bag per sweep (with
        ``_FIELDS_BY_BAG``), else one gather, one product and a sum per part."""
        if self.by_bag:
            return torch.nn.functional.embedding_bag(self.bag_idx, self.table, self.bag_off, mode="sum",
                                                     per_sample_weights=self.bag_w).view(self.f.shape)
        torch.index_select(self.flat, 0, self.idx, out=self.p)
        self.p.view(self.f.shape[0], -1).mul_(self.w)
        for slots, out in self.sums:
            torch.sum(slots, 1, out=out)
        return self.f

    def sweep(self, half, field: Optional[torch.Tensor] = None) -> None:
        """Metropolis flips of the class: where ``F_i h_i > half`` (thresholds ``(R, width)``,
        or a scalar 0 for zero temperature); ``field (width,)`` is added to the local fields."""
        f = self.fields()
        if field is not None:
            f.add_(field)
        # flip where F_i h_i > half, in 3 ops instead of 4: d = half − F_i h_i (F_i = ±1, so the
        # product is exact and d rounds once: d < 0 exactly when F_i h_i > half, d = +0 on a
        # tie), then F_i ← copysign(1, F_i·d) = −F_i where d < 0, F_i where d ≥ 0 (a tie's
        # ±0 carries F_i's sign)
        torch.addcmul(self.zero if isinstance(half, float) else half, self.sg, f, value=-1.0, out=self.x)
        self.x.mul_(self.sg)
        torch.copysign(self.one, self.x, out=self.sg)


def _with_carries(t: torch.Tensor, fill) -> torch.Tensor:
    """Rows ``(D, m)`` of a wide table with a carry row (``fill``) after the first
    ``_ORDERED_SLOTS`` and after every ``_ORDERED_SLOTS - 1`` further ones: each chunk of
    ``_ORDERED_SLOTS`` rows is summed into the carry row that opens the next."""
    carry = torch.full_like(t[:1], fill)
    pieces, j = [t[:_ORDERED_SLOTS]], _ORDERED_SLOTS
    while j < t.shape[0]:
        pieces += [carry, t[j:j + _ORDERED_SLOTS - 1]]
        j += _ORDERED_SLOTS - 1
    return torch.cat(pieces)


def _color_layout(mesh: MeshBatch, H: torch.Tensor, fixed: torch.Tensor, R: int):
    """The annealer's state and tables, built once per call with one host read (the colouring's
    convergence, the class sizes and the largest degree; more reads only if a priority chain is
    longer than 16).

    State columns: per colour, its narrow-table vertices (degree <= 8) then the others, each group
    padded to whole blocks of _BLOCK columns (dummy columns: no table points at them, nothing reads
    them back), then the fixed vertices, then a zero column for unused table slots.

    Returns:
        ``s (R, columns + 1)`` zeros, ``pos (V,)`` each vertex's column, the classes
        (:class:`_ColorClass`, views of ``s``), ``color (V,)`` (-1 fixed), ``free (n,)`` the free
        vertices in column order.
    """
    dev, dt = H.device, H.dtype
    V = mesh.verts.shape[0]
    col = _Coloring(mesh, ~fixed, 64)
    changed = col.run(_COLOR_ROUNDS)
    deg = mesh.degrees
    nbins = 2 * (col.C - 1) + 1                            # (colour, wide) bins, then the fixed
    while True:
        color = col.result()
        key = torch.where(color >= 0, 2 * color + (deg > _NARROW).long(), nbins - 1)
        counts = torch.zeros(nbins, dtype=torch.long, device=dev).index_add_(0, key, torch.ones_like(key))
        # the largest degree of each bin: a class's full-width table is as wide as its own
        # largest degree, not the batch's (the number of chunked sums per sweep then does not
        # grow with the batch's extreme vertex)
        dbin = torch.zeros(nbins, dtype=torch.long, device=dev).scatter_reduce_(0, key, deg, "amax")
        info = torch.cat([changed.long()[None], counts, dbin]).tolist()
        if not info[0]:
            break
        changed = col.run(8)
    cnt, dmax = info[1:1 + nbins], info[1 + nbins:]
    D = max(max(dmax), 1)
    padded = [-(-n // _BLOCK) * _BLOCK for n in cnt[:-1]] + [cnt[-1]]
    pad_t = (counts + _BLOCK - 1) // _BLOCK * _BLOCK           # the same on the device
    pad_t[-1] = counts[-1]
    order = torch.argsort(key, stable=True)                # stable: a class keeps vertex order
    kb = key[order]
    pos = torch.empty(V, dtype=torch.long, device=dev)
    pos[order] = (torch.arange(V, device=dev) - (torch.cumsum(counts, 0) - counts)[kb]
                  + (torch.cumsum(pad_t, 0) - pad_t)[kb])
    Z = sum(padded)                                        # the zero column
    s = torch.zeros(R, Z + 1, dtype=dt, device=dev)
    free = order[:sum(cnt[:-1])]
    nb_all, w_all = _coupling_table(mesh, H, free, pos, D, Z)
    rows = torch.arange(R, device=dev)[:, None] * (Z + 1)
    classes = []
    a_sorted = a_state = 0
    for c in range(col.C - 1):
        parts, nbs, ws, L, width = [], [], [], 0, 0
        for wide in (0, 1):
            n, m = cnt[2 * c + wide], padded[2 * c + wide]
            if n:
                Dt = max(dmax[2 * c + 1], 1) if wide else min(D, _NARROW)
                nb = torch.nn.functional.pad(nb_all[:Dt, a_sorted:a_sorted + n], (0, m - n), value=Z)
                w = torch.nn.functional.pad(w_all[:Dt, a_sorted:a_sorted + n], (0, m - n))
                if Dt > _ORDERED_SLOTS:
                    nb, w = _with_carries(nb, Z), _with_carries(w, 0)
                    Dt = nb.shape[0]
                nbs.append(nb.reshape(-1))
                ws.append(w.reshape(-1))
                parts.append((L, Dt, m, width))
                L, width, a_sorted = L + Dt * m, width + m, a_sorted + n
        if parts:
            idx = (torch.cat(nbs)[None, :] + rows).reshape(-1)
            classes.append(_ColorClass(s, a_state, width, idx, torch.cat(ws), parts))
            a_state += width
    return s, pos, classes, color, free


#: random numbers the annealer hashes at once, at most (about 8 bytes each, a few buffers): on
#: a CPU 2**20, which keeps the hashing in cache (2**22 or more ran 2-7x slower a number); on a
#: GPU enough for a whole level's sweeps in a few blocks up to B ~ 4096 shapes of 500 points,
#: so that the launches of a level's random numbers do not grow with the batch
_RNG_NUMBERS = {"cpu": 1 << 20}
_RNG_NUMBERS_OTHER = 1 << 26


def _rng_block(sweeps: int, numbers_per_sweep: int, device: torch.device) -> int:
    """Sweeps per block of random numbers (the memory bound of ``device``)."""
    cap = _RNG_NUMBERS.get(device.type, _RNG_NUMBERS_OTHER)
    return max(1, min(sweeps, cap // max(numbers_per_sweep, 1)))


def _metropolis_thresholds(hc: torch.Tensor, koff: torch.Tensor, thalf: torch.Tensor, dt: torch.dtype) -> torch.Tensor:
    """``(n, R, F)`` the thresholds ``(T/2) log u`` of ``n`` sweeps: ``u`` the hash of the keys
    ``hc (R, F) + koff (n, 1, 1)`` (``hash_to_unit(mix32(.))``, bit for bit, in fewer ops and
    in place), ``thalf (n, R)`` the halved temperatures."""
    m = 0xFFFFFFFF
    x = torch.add(hc[None], koff).bitwise_and_(m)                # mix32, in place
    x.bitwise_xor_(x >> 16).mul_(0x7FEB352D).bitwise_and_(m)
    x.bitwise_xor_(x >> 15).mul_(0x846CA68B).bitwise_and_(m)
    x.bitwise_xor_(x >> 16)
    # hash_to_unit: (h + 1/2) / 2**32 exactly in float64 (h < 2**32) as one op, then rounded
    c = torch.full((), 2.0 ** -33, dtype=torch.float64, device=x.device)
    u = torch.add(c, x, alpha=2.0 ** -32).to(dt)
    u = u.clamp_max_(1.0 - torch.finfo(dt).eps / 2).log_()
    return u.mul_(thalf[:, :, None])



@functools.lru_cache(maxsize=32)
def _temperatures(sweeps: int, t_start: float, t_end: float, warm_t_start: Optional[float], R: int,
                  dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``(sweeps, R)`` the geometric schedule of each replica (the same at every level: cached;
    callers must not write to it)."""
    return _temperature_rows(sweeps, t_start, t_end, warm_t_start, R, dtype, device, 0, int(sweeps))


#: schedules up to this many sweeps are made whole and cached; longer ones a block at a time
#: inside the sweeps (a million rows took 21 s before the first sweep, past any max_seconds)
_CACHED_SWEEPS = 4096


def _temperature_rows(sweeps: int, t_start: float, t_end: float, warm_t_start: Optional[float], R: int,
                      dtype: torch.dtype, device: torch.device, k0: int, k1: int) -> torch.Tensor:
    """Rows ``k0:k1`` of :func:`_temperatures` (the same bits)."""
    t0 = torch.full((R,), float(t_start), dtype=dtype, device=device)
    if warm_t_start is not None:
        t0[0] = min(float(warm_t_start), float(t_start))
    ratio = (t_end / t0) ** (1.0 / max(int(sweeps) - 1, 1))
    return torch.stack([t0 * ratio ** k for k in range(int(k0), int(k1))])


def ising_energy(mesh: MeshBatch, H: torch.Tensor, signs: torch.Tensor, field: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``Σ_e H_e F_i F_j`` (``+ Σ_v g_v F_v`` with ``field``) per item; ``signs (V,)`` or
    ``(V, R)`` -> ``(B,)`` or ``(B, R)``."""
    e = mesh.edges
    s = signs if signs.dim() == 2 else signs[:, None]
    t = H[:, None] * s[e[:, 0]] * s[e[:, 1]]
    out = torch.zeros(mesh.num_items, s.shape[1], dtype=H.dtype, device=H.device).index_add_(0, mesh.edge_item, t)
    if field is not None:
        out.index_add_(0, mesh.vert_item, field.to(H.dtype)[:, None] * s)
    return out if signs.dim() == 2 else out[:, 0]


def _sweep_classes(classes, half, gcol: Optional[torch.Tensor]) -> None:
    """One Metropolis sweep of every colour class: thresholds ``half (R, F)`` in state columns,
    or the scalar 0.0 (zero temperature)."""
    for cl in classes:
        cl.sweep(half if isinstance(half, float) else half[:, cl.a:cl.a + cl.width],
                 None if gcol is None else gcol[cl.a:cl.a + cl.width])


def _sweep_from_row(classes, half: torch.Tensor, row: torch.Tensor, gcol: Optional[torch.Tensor]) -> None:
    """:func:`_sweep_classes` with the thresholds ``half[row]`` (``half (n, R, F)``, ``row (1,)``
    on the device), then ``row`` advanced by one: a recorded sweep, replayed sweep after sweep."""
    _sweep_classes(classes, half.index_select(0, row)[0], gcol)
    row.add_(1)


def anneal(mesh: MeshBatch, H: torch.Tensor, init: torch.Tensor, fixed: torch.Tensor,
           cfg: Optional[TopologyConfig] = None, seed: int = 0, warm: bool = False,
           field: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Minimize the Ising energy ``Σ_e H_e F_i F_j`` over ``F ∈ {−1, 1}`` by simulated annealing.

    Vertices of one colour are never adjacent, so each colour class is updated in parallel
    (Metropolis) for the whole batch and all ``cfg.anneal_replicas`` at once. Temperatures fall
    geometrically from ``anneal_t_start`` to ``anneal_t_end`` over ``anneal_sweeps``; a few
    zero-temperature sweeps finish, and the replica of lowest energy is kept per item (ties to
    the lowest replica).

    With ``warm``, replica 0 starts from ``init`` at ``anneal_warm_t_start``, keeping
    what earlier levels found, while the other replicas start from +1 at ``t_start``: a
    cluster of wrong signs that single flips at low temperature cannot undo is redone.

    The state ``(R, columns)`` is kept in colour order, so that a class is one slice, and the
    local fields are gathers from padded neighbour tables built once per call: no sparse tensor
    and no host read in the sweeps. The one host read is the colouring's (its convergence, the
    class sizes, the largest degree).

    Args:
        init: ``(V,)`` ±1 start. fixed: ``(V,)`` bool, vertices held at their ``init`` value.
        field: ``(V,)`` optional field term: the energy is ``Σ_e H_e F_i F_j + Σ_v g_v F_v``.
    Returns:
        ``(V,)`` ±1 signs (dtype of ``H``).
    """
    cfg = TopologyConfig() if cfg is None else cfg
    sweeps, greedy_sweeps = int(cfg.anneal_sweeps), int(cfg.anneal_greedy_sweeps)
    warm_t_start = float(cfg.anneal_warm_t_start) if warm else None
    with torch.no_grad():
        dev, dt = H.device, H.dtype
        V = mesh.verts.shape[0]
        R = max(int(cfg.anneal_replicas), 1)
        s0 = init.to(dt)[:, None].repeat(1, R)
        if warm_t_start is not None:
            s0[:, 1:] = torch.where(fixed, init.to(dt), torch.ones_like(init, dtype=dt))[:, None]
        s, pos, classes, color, free = _color_layout(mesh, H, fixed, R)
        s[:, pos] = s0.T
        F = classes[-1].a + classes[-1].width if classes else 0      # the free vertices' columns
        gcol = None
        if field is not None:                                        # the field in state columns
            gcol = torch.zeros(s.shape[1], dtype=dt, device=dev)
            gcol[pos] = field.to(dt)
        # Metropolis: accept when u < exp(-dE / T), i.e. dE < -T log u; with dE = -2 F_i h_i,
        # when F_i h_i > (T log u) / 2 (a threshold <= 0; the halving is exact). The random
        # numbers are keyed by (seed, local vertex, replica, 64 sweep + colour), as before.
        local = torch.arange(V, device=dev) - mesh.verts_first_idx[mesh.vert_item]
        lc = torch.zeros(F, dtype=torch.long, device=dev).index_copy_(0, pos[free], local[free])
        cc = torch.zeros(F, dtype=torch.long, device=dev).index_copy_(0, pos[free], color[free])
        rep = torch.arange(R, device=dev)[:, None]
        h0 = hash_keys(torch.zeros(R, F, dtype=torch.long, device=dev), torch.full((R, F), int(seed), device=dev),
                       lc[None, :].expand(R, -1), rep.expand(-1, F))
        # hash_keys(h0, key) = mix32(h0 * 0x9E3779B1 + key + 0x632BE5AB): its constant part once
        h0 = h0 * 0x9E3779B1 + 0x632BE5AB
        sched = (sweeps, float(cfg.anneal_t_start), float(cfg.anneal_t_end), warm_t_start, R, dt, dev)
        temps = _temperatures(*sched) if sweeps <= _CACHED_SWEEPS else None
        # the key of sweep k is h0 + (64 k + colour): the colour folded in once (int64 sums wrap,
        # so the order of the additions does not change a bit), the sweep offsets made once
        hc = h0 + cc[None, :]
        koff = torch.arange(sweeps, device=dev)[:, None, None] * 64
        # (T log u) / 2 as (T/2) log u: halving is exact, so the product's bits are the same
        thalf = None if temps is None else temps * 0.5
        # the random numbers of a block of sweeps are hashed in one pass of ops; the block bounds
        # the memory (_RNG_NUMBERS)
        block = _rng_block(sweeps, F * R, dev)
        half = None
        # on a GPU one sweep of every class is recorded (after a first eager sweep, which makes
        # the ops' lazy state) and replayed, one launch a sweep (pipeline/graphs.py): a sweep
        # reads its thresholds from the block's rows at a counter on the device and advances
        # it; once per block of thresholds, and once for the zero-temperature sweeps
        replay = graphs.active(dev, "anneal") and bool(classes)
        graph = cooling = None
        for k in budget.rounds(sweeps + greedy_sweeps):
            if k < sweeps and k % block == 0:
                th = thalf[k:k + block] if thalf is not None else _temperature_rows(*sched, k, k + block) * 0.5
                half = _metropolis_thresholds(hc, koff[k:k + block], th, dt)
                graph = None                   # new rows: a new recording
            hk = half[k % block] if k < sweeps else None
            if replay and k > 0:
                if graph is None or cooling != (k < sweeps):
                    cooling = k < sweeps
                    step = (functools.partial(_sweep_from_row, classes, half, torch.full(
                        (1,), k % block, dtype=torch.long, device=dev), gcol) if cooling
                        else functools.partial(_sweep_classes, classes, 0.0, gcol))
                    graph = graphs.capture(step, dev, "anneal")
                    replay = graph is not None
                if graph is not None:
                    graph.replay()
                    continue
            _sweep_classes(classes, hk if k < sweeps else 0.0, gcol)
        s = s[:, pos].T
        E = ising_energy(mesh, H, s, field)                       # (B, R)
        best = torch.argmin(E, 1)                                 # first minimum
        return s.gather(1, best[mesh.vert_item][:, None]).squeeze(1)


def sign_islands(mesh: MeshBatch, signs: torch.Tensor) -> torch.Tensor:
    """``(V,)`` long: a label per vertex, equal for vertices joined by a path of edges whose
    ends have the same sign (the label is the smallest vertex index of the region;
    :func:`~torch_isc.core.segments.edge_components`)."""
    e = mesh.edges
    return edge_components(signs.shape[0], e, (signs[e[:, 0]] < 0) == (signs[e[:, 1]] < 0))


def remove_small_islands(mesh: MeshBatch, signs: torch.Tensor, keep: torch.Tensor, min_vertices: int) -> torch.Tensor:
    """Flip every sign region of fewer than ``min_vertices`` vertices that holds no ``keep``
    vertex (the reconstruction passes the fixed boundary). A region that small is below the
    mesh's resolution: the zero set around a single vertex is a loop within its star (a
    pinched-off wedge tip, a speck around an outlier), which the data cannot place. Where the
    data do hold a feature, the test still finds its points far from the curve and refines,
    and the next level anneals it with more vertices; a feature the refinement stops short of
    (fewer than ``min_points_fit`` points, or the size floor) is lost.
    """
    if min_vertices <= 1:
        return signs
    with torch.no_grad():
        lab = sign_islands(mesh, signs)
        size = segment_count(lab, signs.shape[0])
        pinned = torch.zeros_like(size, dtype=torch.bool).index_fill_(0, lab[keep], True)
        flip = (size[lab] < min_vertices) & ~pinned[lab]
        return torch.where(flip, -signs, signs)


# ------------------------------------------------------------------- where signs come from
class SignSource(Protocol):
    """Where the vertex signs of a level come from (Section 3.2): estimated from the data
    (:class:`IsingSigns`) or read from an inside/outside oracle (:class:`OracleSigns`)."""

    def signs(self, ws: "WorkingSet", ev: "Evidence", level: int) -> torch.Tensor:
        """``(V,)`` ±1 signs of the working set's vertices."""
        ...

    def marks(self, ws: "WorkingSet", values: torch.Tensor, min_len: torch.Tensor) -> Optional[torch.Tensor]:
        """``(T,)`` bool, triangles the source wants split beyond the test (or None)."""
        ...


class IsingSigns:
    """Signs that minimize the Ising energy of the line evidence (eqs. 3.5-3.6), annealed;
    sign regions below the mesh's resolution are then flipped.

    Args:
        topology: the annealing and island settings. evidence: the line-fit settings. seed:
            the annealing's random seed.
    """

    def __init__(self, topology: TopologyConfig, evidence: "EvidenceConfig", seed: int = 0):
        self.cfg, self.evidence, self.seed = topology, evidence, seed
        self._crust = None                                # the crust of the current solve (crust.CrustCache)
        self._parity = None                               # the current level's crust_parity, with its mesh

    def signs(self, ws: "WorkingSet", ev: "Evidence", level: int) -> torch.Tensor:
        from torch_isc.pipeline.evidence import local_fits
        with torch.no_grad():
            mesh = ws.mesh
            fits = local_fits(mesh, ev.moments, ev.fits, self.evidence, noise=ws.noise)
            H = edge_weights(mesh, fits.L, fits.eps, ev.moments.count, self.evidence.min_points_fit,
                             self.cfg.empty_weight, pooled_count=fits.support, reach=fits.reach,
                             noise2=ws.noise ** 2)
            far, sides = None, None
            if self.cfg.unsupported_weight > 0 or self.cfg.cluster_rounds > 0:
                from torch_isc.pipeline.support import support_coupling
                cpl, far = support_coupling(ws, self.cfg.unsupported_weight, self.cfg.unsupported_noise_widths)
                H = H + cpl
            if self.cfg.crust_weight > 0:
                from torch_isc.pipeline.crust import CrustCache, crust_parity
                if level == 0 or self._crust is None:
                    self._crust = CrustCache()            # a new solve (the source serves one solve)
                c = self.cfg
                par, spacing, span = crust_parity(ws, c.crust_noise_tolerances, c.crust_max_length,
                                                  c.crust_noise_spacings, self._crust)
                self._parity = (mesh, par, spacing, span)  # for marks() on the same mesh
                H = H + float(c.crust_weight) * par.to(H.dtype)     # crust_coupling's
                if c.crust_sides > 0 and bool((spacing > 0).any()):
                    from torch_isc.pipeline.crust import crust_sides
                    # the field's sign: the energy's g_v F_v is lowest at F_v = -sign(g_v)
                    sides = -float(c.crust_sides) * crust_sides(mesh, par, spacing)
            fixed = mesh.is_boundary_vert
            init = torch.where(fixed, torch.ones_like(ws.signs), ws.signs)
            field = self._winding_field(ws, level) if self.cfg.winding_weight > 0 else None
            if sides is not None:
                field = sides if field is None else field + sides
            s = anneal(mesh, H, init, fixed, self.cfg, self.seed, warm=level > 0, field=field)
            if self.cfg.cluster_rounds > 0:
                from torch_isc.pipeline.simplify import descend_clusters
                s = descend_clusters(mesh, H, s, fixed, far, self.cfg.cluster_rounds)
            if self.cfg.open_noise_widths > 0 or self.cfg.open_tolerances > 0:
                from torch_isc.pipeline.simplify import open_stage
                s = open_stage(ws, s, fixed, self.cfg)
            if self.cfg.notch_rounds > 0:
                from torch_isc.pipeline.notches import notch_stage
                c = self.cfg
                s = notch_stage(ws, s, fixed, c.notch_rounds, c.notch_coherence, c.notch_cone, c.notch_min_points)
            if self.cfg.channel_fill:
                from torch_isc.pipeline.channels import channel_stage
                s = channel_stage(ws, s, fixed, self.cfg)
            s = remove_small_islands(mesh, s, fixed, self.cfg.min_island_vertices)
            if self.cfg.enclose_chord > 0:
                # last: the island and speck rules would take a one-vertex loop back
                from torch_isc.pipeline.simplify import enclose_stage
                s = enclose_stage(ws, s, self.cfg)
            if ws.blob is not None:
                # last too: a vertex inside a cluster no curve explains (pipeline/blobs.py)
                from torch_isc.pipeline.blobs import blob_stage
                s = blob_stage(ws, s)
            return s

    def _winding_field(self, ws: "WorkingSet", level: int) -> torch.Tensor:
        """``(V,)`` the winding prior's field (pipeline/winding.py). The prior depends on the
        points only: it is made at level 0 (all items) and read by caller item after."""
        from torch_isc.pipeline.winding import winding_field, winding_prior
        prior = getattr(self, "_prior", None)
        if prior is None or level == 0:
            c = self.cfg
            prior = winding_prior(ws.points, ws.point_item, ws.num_items, ws.noise, c.winding_neighbours,
                                  c.winding_sync_iterations, c.winding_smoothing)
            self._prior, self._prior_items = prior, ws.items
        return winding_field(prior, ws.mesh.verts, self._prior_row(ws)[ws.mesh.vert_item], self.cfg.winding_weight)

    def _prior_row(self, ws: "WorkingSet") -> torch.Tensor:
        """``(B,)`` each working item's row of the cached prior."""
        rows = torch.full((int(self._prior_items.max()) + 1,), -1, dtype=torch.long, device=ws.device)
        rows[self._prior_items] = torch.arange(self._prior_items.shape[0], device=ws.device)
        return rows[ws.items]

    def marks(self, ws: "WorkingSet", values: torch.Tensor, min_len: torch.Tensor) -> Optional[torch.Tensor]:
        if self.cfg.crust_refine <= 0 or self.cfg.crust_weight <= 0 or self._crust is None:
            return None
        from torch_isc.pipeline.crust import crust_contradictions
        c = self.cfg
        return crust_contradictions(ws, values, c.crust_refine, c.crust_noise_tolerances, c.crust_max_length,
                                    c.crust_noise_spacings, self._crust, self._parity)


class OracleSigns:
    """Signs read from inside/outside oracles, asked in the caller's coordinates; boundary
    vertices are outside. The oracle also marks triangles next to an interior edge (longer
    than ``min_len`` of its item) at whose midpoint it and the piecewise-linear function
    disagree: vertex signs alone cannot see a thin stroke or a gap passing between vertices.

    Args:
        oracles: one callable per caller's item, ``oracle(points (M, 2)) -> (M,)`` bool (True
            inside), or one batched callable ``oracle(points (M, 2), item (M,)) -> (M,)``.
    """

    def __init__(self, oracles: Union[Callable, Sequence[Optional[Callable]]]):
        self.oracles = oracles

    def inside(self, ws: "WorkingSet", x: torch.Tensor, item: torch.Tensor) -> torch.Tensor:
        """``(M,)`` bool at normalized points ``x (M, 2)`` of working items ``item (M,)``
        (non-decreasing)."""
        b = ws.items[item]
        xc = ws.caller_points(x, item)
        if callable(self.oracles):                                  # batched: one call for all items
            inside = _ask(self.oracles, "sign oracle", x.device, xc, b)
            if inside.shape[0] != xc.shape[0]:
                raise SignOracleError(f"sign oracle returned {inside.shape[0]} values for {xc.shape[0]} points")
            return inside
        out = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
        counts = torch.bincount(item, minlength=ws.num_items)
        starts = first_index(counts).tolist()
        for b, s0, n in zip(ws.items.tolist(), starts, counts.tolist()):   # one call per item
            o = self.oracles[b]
            if o is None:
                raise SignOracleError(f"item {b}: sign oracles must be given for every item or none")
            if n:
                got = _ask(o, f"item {b}: sign oracle", x.device, xc[s0:s0 + n])
                if got.shape[0] != n:
                    raise SignOracleError(f"item {b}: sign oracle returned {got.shape[0]} values for {n} points")
                out[s0:s0 + n] = got
        return out

    def signs(self, ws: "WorkingSet", ev: "Evidence", level: int) -> torch.Tensor:
        mesh = ws.mesh
        inside = self.inside(ws, mesh.verts, mesh.vert_item)
        out = torch.where(inside, -1.0, 1.0).to(ws.dtype)
        out[mesh.is_boundary_vert] = 1.0
        return out

    def marks(self, ws: "WorkingSet", values: torch.Tensor, min_len: torch.Tensor) -> Optional[torch.Tensor]:
        mesh = ws.mesh
        e = mesh.edges
        v = mesh.verts.detach()
        inside = self.inside(ws, 0.5 * (v[e[:, 0]] + v[e[:, 1]]), mesh.edge_item)
        pl_inside = (values[e[:, 0]] + values[e[:, 1]]) < 0
        long = (v[e[:, 0]] - v[e[:, 1]]).norm(dim=1) > min_len[mesh.edge_item]
        bad = (inside != pl_inside) & long & ~mesh.is_boundary_edge
        out = torch.zeros(mesh.faces.shape[0], dtype=torch.bool, device=v.device)
        ef = mesh.edge_faces[bad].reshape(-1)
        out[ef[ef >= 0]] = True
        return out


class SignOracleError(PointSetError):
    """A sign oracle that answered with the wrong number of values, or was missing."""


def _ask(oracle: Callable, what: str, device, *args) -> torch.Tensor:
    """``oracle(*args)`` as a flat bool tensor on ``device``; an oracle that raises or answers
    with something that is not an array of booleans is a :class:`SignOracleError` (one line)."""
    try:
        got = oracle(*args)
    except Exception as e:
        raise SignOracleError(f"{what} raised {type(e).__name__}: {one_line(e, '(no message)')}") from e
    try:
        t = torch.as_tensor(got, device=device)
    except (TypeError, ValueError, RuntimeError):
        raise SignOracleError(f"{what} returned {type(got).__name__}, not an array of booleans") from None
    if t.dtype == torch.bool:
        return t.reshape(-1)
    # a number is not a side: a signed distance read as bool would be "inside" wherever it is
    # not 0 (both sides of the curve), so only integer 0/1 answers pass besides booleans
    if t.is_floating_point() or t.is_complex() or t.numel() and not bool(((t == 0) | (t == 1)).all()):
        raise SignOracleError(f"{what} returned {t.dtype} values, not booleans (True inside; e.g. f(p) < 0 "
                              f"for a function negative inside)")
    return t.bool().reshape(-1)
