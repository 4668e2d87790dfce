"""Unsupported tips: a vertex whose sign pokes the zero set out into empty space.

After the geometry fit, some converged curves still carry spikes: one vertex of a region's sign
standing among the other sign's vertices (a sharp corner's line fits vote for the wrong side, a
few noisy points tip the annealer), so the zero set runs out around it and back, across a
triangle or two where no data point lies. The test sees such pieces (the coverage test marks
their triangles) but cannot resolve them when the triangles are already at their split floor
(a few noise widths), and one vertex wide they are no region the speck rules remove. They are
the largest part of the Hausdorff distance of many noisy results that have the right topology.

The rule (run in the band stage's spike rounds, :mod:`torch_isc.pipeline.band`, before each
refit). Every edge ``(i, j)`` has one place where a crossing on it would be, given the fitted
magnitudes: ``x_ij = v_i + |f_i| / (|f_i| + |f_j|) (v_j − v_i)``, whatever the signs (a flip of a
vertex keeps its magnitude). A crossing is *supported* when a data point lies within its reach
of that place: the item's tested tolerance (the distance the test allows), or one sample
spacing where the samples are sparser (the distance to the farthest of the point's
``noise_neighbours`` nearest over half their count: a quarter of the 8th's with the default;
between the samples of a clean sparse curve, at a sharp corner, the true curve is that far
from the data). A vertex ``v`` flips when:

- it is simple (its link has one run of each sign, :meth:`ImplicitCurve.simple_vertices`): the
  flip keeps the topology;
- most of its edges cross (more than stay): it is a tip, the flip shortens the curve;
- at least half of its crossings are unsupported;
- every crossing the flip would make is supported: the curve leaves empty space and stays
  with the data;
- and it is not pinned: its sign region has at least :data:`MIN_REGION` vertices (a small
  closed curve of a few points has gaps wider than the tolerance between its points, and would
  shrink to nothing), and the data in its star do not surround it
  (:func:`surrounded_vertices`).

Adjacent candidates do not flip together (the larger count of unsupported crossings wins, ties
the lower index): a flip changes its neighbours' links. Fixed shapes; the only host reads are
the region labelling's convergence checks (:func:`~torch_isc.core.segments.edge_components`,
about a dozen a solve by gpu_floor). The caller refits the magnitudes for the new signs.
"""
from __future__ import annotations

import torch

from torch_isc.core.curve import ImplicitCurve
from torch_isc.core.mesh import MeshBatch
from torch_isc.pipeline.simplify import occupied_sectors

__all__ = ["crossing_places", "crossing_support", "surrounded_vertices", "region_sizes", "unsupported_tips",
           "MIN_REGION"]


def crossing_places(mesh: MeshBatch, values: torch.Tensor) -> torch.Tensor:
    """``(E, 2)``: where a crossing on each edge would be, from the magnitudes ``|values|`` (the
    midpoint where both are zero)."""
    e = mesh.edges
    v = mesh.verts.detach()
    fa, fb = values[e[:, 0]].abs(), values[e[:, 1]].abs()
    den = fa + fb
    t = torch.where(den > 0, fa / den.clamp_min(torch.finfo(den.dtype).tiny), torch.full_like(den, 0.5))
    return v[e[:, 0]] + t[:, None].to(v.dtype) * (v[e[:, 1]] - v[e[:, 0]])


def crossing_support(mesh: MeshBatch, values: torch.Tensor, points: torch.Tensor, face: torch.Tensor,
                     reach: torch.Tensor) -> torch.Tensor:
    """``(E,)`` bool: whether a data point lies within its ``reach (P,)`` of each edge's crossing
    place (:func:`crossing_places`), among the points located in a triangle of the edge or next
    to one (a place farther from the data than a triangle is unsupported)."""
    with torch.no_grad():
        x = crossing_places(mesh, values)
        ok = face >= 0
        f = face.clamp_min(0)
        tri = torch.cat([f[:, None], mesh.face_neighbors[f]], 1)             # (P, 4)
        has = (tri >= 0) & ok[:, None]
        eid = mesh.face_edges[tri.clamp_min(0)].reshape(points.shape[0], 12)  # (P, 12)
        d = (x[eid] - points.to(x.dtype)[:, None, :]).norm(dim=2) - reach.to(x.dtype)[:, None]
        d = torch.where(has.repeat_interleave(3, 1), d, torch.full_like(d, float("inf")))
        out = torch.full((mesh.edges.shape[0],), float("inf"), dtype=x.dtype, device=x.device)
        return out.scatter_reduce(0, eid.reshape(-1), d.reshape(-1), "amin") <= 0


def surrounded_vertices(mesh: MeshBatch, points: torch.Tensor, face: torch.Tensor, sectors: int = 8,
                        need: int = 6) -> torch.Tensor:
    """``(V,)`` bool: the vertices with data all around them: the points located in their star
    occupy at least ``need`` of ``sectors`` equal angular sectors about the vertex. A vertex
    inside a small closed curve of few points is surrounded (the gaps between its points are
    no evidence against its crossings); a spike's tip sees the data on the side of its base,
    and a vertex beside a noisy stretch of curve about half the sectors."""
    with torch.no_grad():
        v = mesh.verts.detach()
        V = v.shape[0]
        vid = mesh.faces[face.clamp_min(0)]                                # (P, 3)
        use = (face >= 0)[:, None].expand(-1, 3)
        return occupied_sectors(points.detach().to(v.dtype)[:, None, :] - v[vid], vid, use, V, sectors) >= need


#: a vertex whose sign region has fewer vertices than this never flips: a small closed curve of a
#: few points (a satellite) has gaps between its points wider than the tolerance, and every
#: flip would shrink it toward nothing; a spike stands on a large region
MIN_REGION = 8


def region_sizes(mesh: MeshBatch, signs: torch.Tensor) -> torch.Tensor:
    """``(V,)`` the number of vertices of each vertex's sign region (connected along edges whose
    ends agree)."""
    from torch_isc.core.segments import edge_components
    with torch.no_grad():
        e = mesh.edges
        lab = edge_components(signs.shape[0], e, signs[e[:, 0]] == signs[e[:, 1]])
        return torch.bincount(lab, minlength=signs.shape[0])[lab]


def unsupported_tips(mesh: MeshBatch, signs: torch.Tensor, supported: torch.Tensor,
                     pinned: torch.Tensor) -> torch.Tensor:
    """``(V,)`` bool: the vertices that flip in one round of the rule (module docstring), from
    the signs ``(V,)`` (±1), ``supported (E,)`` bool (a crossing on the edge would be near the
    data) and ``pinned (V,)`` bool (never flip)."""
    with torch.no_grad():
        V = signs.shape[0]
        e = mesh.edges
        a, b = e[:, 0], e[:, 1]
        cross = signs[a] != signs[b]
        idx = torch.cat([a, b])

        def count(mask: torch.Tensor) -> torch.Tensor:
            return torch.zeros(V, dtype=torch.long, device=signs.device).index_add_(0, idx, mask.long().repeat(2))

        n_old, n_new = count(cross), count(~cross)
        bad_old, bad_new = count(cross & ~supported), count(~cross & ~supported)
        simple = ImplicitCurve(mesh, signs, validate=False).simple_vertices()
        unsup = (2 * bad_old >= n_old) & (bad_old > 0)
        cand = simple & ~pinned & (n_new < n_old) & unsup & (bad_new == 0)
        # an independent set: of two adjacent candidates the one with the larger gain flips
        key = bad_old * (V + 1) + (V - torch.arange(V, device=signs.device))
        both = cand[a] & cand[b]
        lose = torch.where(key[a] < key[b], a, b)
        lost = torch.zeros(V + 1, dtype=torch.bool, device=signs.device).index_fill_(
            0, torch.where(both, lose, V), True)[:V]                            # no host read
        return cand & ~lost
