"""The dimension-specific pieces of the method behind one small interface.

Everything else (the Ising model and annealer, the L-BFGS fit given its matrices, the
working set, the test's bookkeeping, relaxation's step control) is written against
:class:`SimplexKernel`, so a tetrahedral kernel (implicit simplicial *surfaces*) can follow by
implementing the same methods for ``d = 3``. :data:`TRIANGLES` is the 2D one.

A simplex of a ``d``-dimensional mesh has ``d + 1`` corners; its facet ``k`` is the one
opposite corner ``k``. Shapes below use ``K = d + 1`` corners, ``T`` simplices, ``P`` points.
The zero set of a linear function on a simplex is a piece of hyperplane: for triangles a
segment with two end points, stored as ``(T, d, d)`` (``d`` points of ``d`` coordinates).
"""
from __future__ import annotations

import math
from typing import Protocol, Sequence, Tuple

import torch

from torch_isc.core.segments import sym2_eigvals, sym2_eigvec

__all__ = ["SimplexKernel", "Triangles", "TRIANGLES"]


class SimplexKernel(Protocol):
    """What the pipeline asks of a simplex type (see :class:`Triangles` for the 2D one)."""
    dim: int
    #: corner pairs ``(first, second)`` of the simplex's edges, in the mesh's edge order
    edge_corners: Tuple[Sequence[int], Sequence[int]]

    def volumes(self, corners: torch.Tensor) -> torch.Tensor: ...
    def bary_gradients(self, corners: torch.Tensor) -> torch.Tensor: ...
    def quality(self, corners: torch.Tensor) -> torch.Tensor: ...
    def barycentric(self, corners: torch.Tensor, points: torch.Tensor) -> torch.Tensor: ...
    def barycentric_frames(self, corners: torch.Tensor) -> torch.Tensor: ...
    def barycentric_from_frames(self, frames: torch.Tensor, points: torch.Tensor) -> torch.Tensor: ...
    def longest_edge(self, corners: torch.Tensor) -> torch.Tensor: ...
    def hyperplane_fit(self, scatter: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]: ...
    def principal_spread(self, scatter: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]: ...
    def edge_crossings(self, corners: torch.Tensor, values: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]: ...
    def zero_set_pieces(self, corners: torch.Tensor, values: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]: ...
    def piece_distance2(self, pieces: torch.Tensor, has: torch.Tensor, points: torch.Tensor,
                        cand: torch.Tensor) -> torch.Tensor: ...
    def split_children(self, faces: torch.Tensor, mids: torch.Tensor, marked_corners: torch.Tensor
                       ) -> Tuple[torch.Tensor, torch.Tensor]: ...


def _cross(u: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    return u[..., 0] * w[..., 1] - u[..., 1] * w[..., 0]


class Triangles:
    """The 2D kernel: triangles, lines, segments.

    Example:
        >>> tri = torch.tensor([[[0., 0.], [1., 0.], [0., 1.]]])
        >>> TRIANGLES.volumes(tri).tolist()                      # twice the signed area
        [1.0]
        >>> TRIANGLES.barycentric(tri, torch.tensor([[0.25, 0.25]])).tolist()
        [[0.5, 0.25, 0.25]]
    """
    dim = 2
    # edge k of a triangle is the one opposite corner k: corners (k+1, k+2)
    edge_corners = ([1, 2, 0], [2, 0, 1])

    def volumes(self, corners: torch.Tensor) -> torch.Tensor:
        """``(T,)`` the determinants of eq. 2.2 (twice the signed areas) of ``corners (T, 3, 2)``."""
        a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
        return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])

    def bary_gradients(self, corners: torch.Tensor) -> torch.Tensor:
        """``(T, 3, 2)`` the constant gradients of the barycentric coordinates (rows of ``G_t``):
        the edge opposite each corner rotated inward, over twice the area."""
        e = corners.roll(1, 1) - corners.roll(-1, 1)                # edge opposite k: v[k+2]-v[k+1]
        det = self.volumes(corners)
        # rotate (x, y) -> (-y, x) gives the inward normal for a positive triangle
        g = torch.stack([-e[..., 1], e[..., 0]], -1)
        return g / det[:, None, None]

    def quality(self, corners: torch.Tensor) -> torch.Tensor:
        """``(T,)`` shape quality in (−∞, 1]: 4√3·area / Σ edge², 1 for equilateral."""
        d = corners.roll(-1, 1) - corners                            # (T, 3, 2), in the order of [1, 2, 0]
        d2 = d * d
        # the sums of squares in the order of .sum(-1).sum(-1), written out (short reductions
        # are slow on a CPU)
        l2 = ((d2[:, 0, 0] + d2[:, 0, 1]) + (d2[:, 1, 0] + d2[:, 1, 1])) + (d2[:, 2, 0] + d2[:, 2, 1])
        return 2.0 * math.sqrt(3.0) * self.volumes(corners) / l2.clamp_min(torch.finfo(corners.dtype).tiny)

    def barycentric(self, corners: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """``(P, 3)`` barycentric coordinates of ``points (P, 2)`` in ``corners (P, 3, 2)``."""
        a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
        det = _cross(b - a, c - a)
        l0 = _cross(c - b, points - b)
        l1 = _cross(a - c, points - c)
        l2 = _cross(b - a, points - a)
        return torch.stack([l0, l1, l2], 1) / det[:, None]

    def barycentric_frames(self, corners: torch.Tensor) -> torch.Tensor:
        """``(T, 13)`` what :meth:`barycentric` needs of each triangle, computed once for
        many points: the origin and the edge of each coordinate's cross product and the
        determinant. :meth:`barycentric_from_frames` then gives the same bits."""
        a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
        det = _cross(b - a, c - a)
        origin = torch.stack([b, c, a], 1).flatten(1)
        edge = torch.stack([c - b, a - c, b - a], 1).flatten(1)
        return torch.cat([origin, edge, det[:, None]], 1)

    def barycentric_from_frames(self, frames: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """``(P, 3)`` barycentric coordinates of ``points (P, 2)`` from the
        :meth:`barycentric_frames` rows ``frames (P, 13)`` of their triangles."""
        origin = frames[:, :6].view(-1, 3, 2)
        edge = frames[:, 6:12].view(-1, 3, 2)
        w = points[:, None, :] - origin
        return (edge[..., 0] * w[..., 1] - edge[..., 1] * w[..., 0]) / frames[:, 12:]

    def longest_edge(self, corners: torch.Tensor) -> torch.Tensor:
        """``(T,)`` the length of each simplex's longest edge."""
        return (corners[:, [1, 2, 0]] - corners).norm(dim=2).max(1).values

    def hyperplane_fit(self, scatter: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """The least-squares line of points with covariance ``scatter (T, 2, 2)``: ``(T,)`` the
        mean squared distance to it (the smallest eigenvalue, >= 0) and ``(T, 2)`` its unit
        normal (``(0, 1)`` for isotropic or empty data)."""
        a, b, d = scatter[:, 0, 0], scatter[:, 0, 1], scatter[:, 1, 1]
        small, _ = sym2_eigvals(a, b, d)
        v = sym2_eigvec(a, b, d, small)
        nv = v.norm(dim=1, keepdim=True)
        iso = nv.squeeze(1) <= 1e-30
        up = torch.stack([torch.zeros_like(a), torch.ones_like(a)], 1)      # (0, 1), made on the device
        normal = torch.where(iso[:, None], up, v / nv.clamp_min(1e-30))
        return small.clamp_min(0), normal

    def principal_spread(self, scatter: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """``(T,)`` the largest and the smallest (>= 0) variance of points with covariance
        ``scatter (T, 2, 2)``."""
        small, large = sym2_eigvals(scatter[:, 0, 0], scatter[:, 0, 1], scatter[:, 1, 1])
        return large, small.clamp_min(0)

    def edge_crossings(self, corners: torch.Tensor, values: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """Where the linear function with corner ``values (T, 3)`` crosses 0 on each edge (in
        :attr:`edge_corners` order): ``(T, 3, 2)`` points (by linear interpolation; any value
        where the edge does not change sign) and ``(T, 3)`` bool, whether it does."""
        a, b = self.edge_corners
        fa, fb = values[:, a], values[:, b]
        cross = (fa < 0) != (fb < 0)
        t = fa / torch.where(fa != fb, fa - fb, torch.ones_like(fa))
        return corners[:, a] + t[..., None] * (corners[:, b] - corners[:, a]), cross

    def zero_set_pieces(self, corners: torch.Tensor, values: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """The zero-set segment of every triangle: ``(T, 2, 2)`` end points and ``(T,)`` bool
        (whether the triangle holds one)."""
        # corners (k+1, k+2) of edge k by rolls, not list indexing (the same values, faster)
        fa, fb = values.roll(-1, 1), values.roll(1, 1)
        cross = (fa < 0) != (fb < 0)
        t = fa / torch.where(cross, fa - fb, torch.ones_like(fa))
        ca = corners.roll(-1, 1)
        pts = ca + t[..., None] * (corners.roll(1, 1) - ca)                       # (T,3,2)
        has = cross.sum(1) == 2
        order = torch.argsort((~cross).to(torch.int8), dim=1, stable=True)[:, :2]
        return pts.gather(1, order[..., None].expand(-1, -1, 2)), has

    def piece_distance2(self, pieces: torch.Tensor, has: torch.Tensor, points: torch.Tensor,
                        cand: torch.Tensor) -> torch.Tensor:
        """``(P,)`` the smallest squared distance of each point to the pieces of its candidate
        simplices ``cand (P, K)`` (-1: none; inf when no candidate holds a piece)."""
        # gathers by index_select and sums of two written out: the same values, several times
        # faster on a CPU than advanced indexing and reductions over a dim of 2
        c = cand.clamp_min(0)
        valid = (cand >= 0) & has.index_select(0, c.reshape(-1)).view(c.shape)
        s = pieces.index_select(0, c.reshape(-1)).view(*c.shape, 2, 2)     # (P,K,2,2)
        p = points.to(pieces.dtype)[:, None, :]
        a, d = s[:, :, 0], s[:, :, 1] - s[:, :, 0]
        pd, dd = (p - a) * d, d * d
        tt = ((pd[..., 0] + pd[..., 1]) / (dd[..., 0] + dd[..., 1]).clamp_min(torch.finfo(pieces.dtype).tiny)).clamp(0, 1)
        q = a + tt[..., None] * d
        e = (p - q) ** 2
        d2 = e[..., 0] + e[..., 1]
        d2 = torch.where(valid, d2, torch.full_like(d2, float("inf")))
        return d2.min(1).values

    def split_children(self, faces: torch.Tensor, mids: torch.Tensor, marked_corners: torch.Tensor
                       ) -> Tuple[torch.Tensor, torch.Tensor]:
        """The rule of Fig. 7: a triangle with three marked corners splits into four, one with
        two into two (through the midpoint of the edge joining them), others stay.

        Args:
            faces: ``(T, 3)`` corner vertex ids. mids: ``(T, 3)`` the id of the new vertex on
                edge ``k`` (any value where the edge is not split). marked_corners: ``(T, 3)`` bool.
        Returns:
            ``(T, 4, 3)`` children (padded by repeats) and ``(T,)`` their number; every child
            keeps the parent's orientation.
        """
        c = marked_corners.sum(1)
        nchild = torch.where(c == 3, 4, torch.where(c == 2, 2, 1))
        v0, v1, v2 = faces[:, 0], faces[:, 1], faces[:, 2]
        m0, m1, m2 = mids[:, 0], mids[:, 1], mids[:, 2]
        four = torch.stack([torch.stack([v0, m2, m1], 1), torch.stack([v1, m0, m2], 1),
                            torch.stack([v2, m1, m0], 1), torch.stack([m0, m1, m2], 1)], 1)   # (T,4,3)
        # two-way split: k = the unmarked corner, m = midpoint of the opposite edge
        k = torch.argmin(marked_corners.to(torch.int8), 1)
        vk = faces.gather(1, k[:, None]).squeeze(1)
        vk1 = faces.gather(1, ((k + 1) % 3)[:, None]).squeeze(1)
        vk2 = faces.gather(1, ((k + 2) % 3)[:, None]).squeeze(1)
        mk = mids.gather(1, k[:, None]).squeeze(1)
        two = torch.stack([torch.stack([vk, vk1, mk], 1), torch.stack([vk, mk, vk2], 1)], 1)   # (T,2,3)
        one = faces[:, None, :]
        two_pad = torch.cat([two, one, one], 1)
        one_pad = one.expand(-1, 4, -1)
        cand = torch.where((c == 3)[:, None, None], four, torch.where((c == 2)[:, None, None], two_pad, one_pad))
        return cand, nchild


#: the kernel of 2D meshes
TRIANGLES = Triangles()
