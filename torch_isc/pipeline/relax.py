"""RelaxMesh (Section 3.5): gradient descent on ``U = κ_D U_D + κ_E U_E``.

``U_D`` (eqs. 3.7-3.8) pushes vertices away from the data and equalizes their
distances to it; ``U_E`` (eq. 3.9) pulls neighbours together toward equilateral
triangles. Corners of the outer boundary stay fixed and other boundary vertices slide
along their side. Each item takes its own step, and a step is accepted only if it
keeps every triangle of the item positively oriented, keeps triangle quality above a
floor (no slivers), and lowers the item's ``U`` with the points re-partitioned.
Dimension-free except for the quality measure and point location it calls.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional, Tuple

import torch

from torch_isc.core.segments import segment_any, segment_max, segment_sum

from torch_isc.core.locate import barycentric, locate_walk
from torch_isc.core.mesh import MeshBatch
from torch_isc.pipeline.knobs import check_section, knob
from torch_isc.pipeline import budget

if TYPE_CHECKING:
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["RelaxConfig", "relax_stage", "mesh_energy", "degree_weights", "relax_mesh"]


@dataclass
class RelaxConfig:
    """RelaxMesh (flat keys of configs/default.yaml)."""
    #: gradient steps per level; 0 disables
    relax_iterations: int = knob(25, ge=0)
    kappa_data: float = knob(1.0, gt=0)
    kappa_edge: float = knob(0.25, gt=0)
    #: no step may bring a triangle's quality below this (no slivers)
    min_quality: float = knob(0.15, ge=0, lt=1)
    #: the largest vertex move of a step, in units of the vertex's shortest edge
    relax_max_move: float = knob(0.3, gt=0, le=1)
    #: step halvings tried before an item's step is given up
    relax_max_backtracks: int = knob(6, gt=0)
    #: relax only items whose estimated noise is at most this fraction of their tolerance
    #: (in a noise band wider than the tolerance "away from the data" says nothing)
    relax_noisy: float = knob(0.5, ge=0)

    def __post_init__(self):
        check_section(self)


def mesh_energy(mesh: MeshBatch, verts: torch.Tensor, points: torch.Tensor, face: torch.Tensor,
                kappa_data: float, kappa_edge: float, rho: torch.Tensor, n_points: torch.Tensor,
                min_dist: torch.Tensor, edge_sel: Optional[torch.Tensor] = None,
                nu_e: Optional[torch.Tensor] = None, consts: Optional[tuple] = None) -> torch.Tensor:
    """``(B,)`` the mesh energy of every item at vertex positions ``verts (V, 2)``.

    Args:
        face: ``(P,)`` each point's triangle (-1: ignored). rho: ``(B,)`` mesh diameters.
        n_points: ``(B,)`` points per item. min_dist: ``(B,)`` distance guard for ``1/|v−p|``.
        edge_sel: optional indices of the edges to sum (the edges of the items wanted; the
            other items' energies are then meaningless).
        nu_e: optional ``(E,)`` :func:`degree_weights` of ``mesh`` (computed when None).
        consts: optional :func:`_energy_constants` of the same arguments (computed when None).
    """
    B = mesh.num_items
    dt = verts.dtype
    guard_t, n_v, rho2 = _energy_constants(mesh, rho, n_points, min_dist) if consts is None else consts
    f = face.clamp_min(0)
    vid = mesh.faces[f]                                             # (P,3)
    guard = guard_t[torch.where(face >= 0, f, mesh.faces.shape[0])]
    dist = (verts[vid] - points.to(dt)[:, None, :]).norm(dim=2)
    inv = torch.maximum(dist, guard[:, None]).reciprocal()          # 1 / max(|v − p|, guard)
    phi = segment_sum(inv.reshape(-1), vid.reshape(-1), verts.shape[0])
    phi = phi / n_v
    e, ei = mesh.edges, mesh.edge_item
    nu_e = degree_weights(mesh) if nu_e is None else nu_e
    if edge_sel is not None:
        e, ei, nu_e = e[edge_sel], ei[edge_sel], nu_e[edge_sel]
    UD = segment_sum((phi[e[:, 0]] - phi[e[:, 1]]) ** 2, ei, B) * rho2
    l2 = ((verts[e[:, 0]] - verts[e[:, 1]]) ** 2).sum(1)
    UE = segment_sum(nu_e.to(dt) * l2, ei, B) / rho2
    return kappa_data * UD + kappa_edge * UE


def _energy_constants(mesh: MeshBatch, rho: torch.Tensor, n_points: torch.Tensor, min_dist: torch.Tensor):
    """What :func:`mesh_energy` uses of its arguments that its evaluations of one relaxation
    share: the distance guard per triangle with an infinite one after the last (an ignored
    point adds 1/inf = 0), the points per vertex's item (at least 1), ``rho²``."""
    guard = torch.cat([min_dist[mesh.face_item], min_dist.new_full((1,), float("inf"))])
    return guard, n_points[mesh.vert_item].clamp_min(1), rho ** 2


def degree_weights(mesh: MeshBatch) -> torch.Tensor:
    """``(E,)`` ``ν_i ν_j`` of eq. 3.9 per edge, ``ν`` a vertex's degree over its item's mean
    degree (topology only: a relaxation computes it once)."""
    deg = mesh.degrees.to(mesh.dtype)
    mdeg = segment_sum(deg, mesh.vert_item, mesh.num_items) / \
        mesh.verts_per_item.to(deg.dtype).clamp_min(1)
    nu = deg / mdeg[mesh.vert_item]
    return nu[mesh.edges[:, 0]] * nu[mesh.edges[:, 1]]


def relax_mesh(mesh: MeshBatch, points: torch.Tensor, point_item: torch.Tensor, face: torch.Tensor,
               cfg: Optional[RelaxConfig] = None, active: Optional[torch.Tensor] = None
               ) -> Tuple[MeshBatch, torch.Tensor, torch.Tensor]:
    """Relax the interior of every item's mesh: ``cfg.relax_iterations`` steps.

    Each step tries the step lengths ``s, s/2, s/4, ...`` in turn and takes the first that
    passes the mesh checks (orientation, quality floor) and lowers ``U``. The mesh checks of
    all lengths are one stacked evaluation; only the first length that passes them is
    re-located and measured (a further round for the items whose ``U`` went up), so the host
    reads a few flags per step, whatever the batch.

    Returns the relaxed mesh, the points' new triangles ``(P,)`` and barycentrics ``(P, 3)``.
    """
    cfg = RelaxConfig() if cfg is None else cfg
    iterations, kappa_data, kappa_edge, min_quality = (cfg.relax_iterations, cfg.kappa_data, cfg.kappa_edge,
                                                       cfg.min_quality)
    max_move, K = cfg.relax_max_move, int(cfg.relax_max_backtracks)
    B = mesh.num_items
    dev, dt = mesh.device, mesh.dtype
    with torch.no_grad():
        v = mesh.verts.detach().clone()
        V, T = v.shape[0], mesh.faces.shape[0]
        vi = mesh.vert_item
        bbox = mesh.item_bbox()
        rho = (bbox[:, 2:] - bbox[:, :2]).norm(dim=1)
        n_points = segment_sum((face >= 0).to(dt), point_item, B)
        min_dist = 1e-4 * rho
        corner = mesh.is_corner_vert[:, None]
        side = (mesh.is_boundary_vert[:, None] & ~corner)
        sdir = mesh.boundary_edge_dir
        e = mesh.edges
        el = (v[e[:, 0]] - v[e[:, 1]]).norm(dim=1)
        # shortest incident edge per vertex bounds its move
        short = torch.full((V,), float("inf"), dtype=dt, device=dev)
        short = short.scatter_reduce(0, torch.cat([e[:, 0], e[:, 1]]), torch.cat([el, el]), "amin")
        mesh.face_neighbors                       # cached here, so the trial meshes share it
        nu_e = degree_weights(mesh)
        consts = _energy_constants(mesh, rho, n_points, min_dist)
        q0 = mesh.quality(v)
        floor = torch.minimum(q0, torch.full_like(q0, min_quality)).repeat(K)
        # trial k of item b is row k * B + b of the stacked mesh checks
        stack_item = (mesh.face_item[None, :] + B * torch.arange(K, device=dev)[:, None]).reshape(-1)
        trial = torch.arange(K, device=dev)[:, None]
        halves = torch.pow(0.5, trial.to(dt))                               # exact powers of two
        vrow = torch.arange(V, device=dev)
        active = torch.ones(B, dtype=torch.bool, device=dev) if active is None else active.clone()
    rounds: list = []       # (positions, energy with its graph, accepted) of the last step's trials
    for _ in budget.rounds(iterations):
        if not rounds:
            vv = v.clone().requires_grad_(True)
            with torch.enable_grad():
                U = mesh_energy(mesh, vv, points, face, kappa_data, kappa_edge, rho, n_points, min_dist, nu_e=nu_e,
                                consts=consts)
                g, = torch.autograd.grad(U.sum(), vv)
            U = U.detach()
        else:               # an accepted trial's energy is this step's: its graph gives the gradient
            g = torch.zeros_like(v)
            with torch.enable_grad():                   # the caller may run under no_grad
                for vk, Ut, ok in rounds:
                    gr, = torch.autograd.grad(Ut.sum(), vk)
                    g = torch.where(ok[vi][:, None], gr, g)
            U = U_next
        rounds = []
        with torch.no_grad():
            d = -g
            d = torch.where(side, (d * sdir).sum(1, keepdim=True) * sdir, d)
            d = torch.where(corner | ~active[vi][:, None], torch.zeros_like(d), d)
            # step so that the largest move is max_move of the vertex's shortest edge
            ratio = d.norm(dim=1) / short
            worst = segment_max(ratio, vi, B, fill=0)
            step = torch.where(worst > 0, max_move / worst.clamp_min(torch.finfo(dt).tiny), torch.zeros_like(worst))
            lengths = step * halves                                         # (K,B) the halvings
            vt = v + lengths[:, vi, None] * d                               # (K,V,2)
            # vt[:, faces] by index_select (the same values, faster on a CPU)
            q = mesh.kernel.quality(vt.index_select(1, mesh.faces.reshape(-1)).reshape(K * T, 3, 2))
            bad = segment_any((q <= 0) | (q < floor), stack_item, K * B).view(K, B)     # q has the sign of the area
            passes = ~bad & active                                          # (K,B)
            accepted = torch.zeros_like(active)
            v_new, face_new, U_next = v, face, U
            if not bool(passes.any()):
                break                                   # no item can move: every later step is the same
            while True:                 # round: each item's first untried length that passes the checks
                has = passes.any(0)
                k = torch.argmax(passes.to(torch.int8), 0)
                vk = torch.where(has[vi][:, None], vt[k[vi], vrow], v)
                ft, _ = locate_walk(mesh.with_verts(vk), points, point_item, face, return_bary=False)
                vk.requires_grad_(True)
                with torch.enable_grad():
                    Ut = mesh_energy(mesh, vk, points, ft, kappa_data, kappa_edge, rho, n_points, min_dist, nu_e=nu_e,
                                     consts=consts)
                ok = has & (Ut.detach() < U)
                rounds.append((vk, Ut, ok))
                v_new = torch.where(ok[vi][:, None], vk.detach(), v_new)
                face_new = torch.where(ok[point_item], ft, face_new)
                U_next = torch.where(ok, Ut.detach(), U_next)
                accepted |= ok
                passes = passes & (trial > k) & ~ok                         # the lengths left to try
                again, moved = torch.stack([passes.any(), accepted.any()]).tolist()
                if not again:
                    break
            active = active & accepted & (step > 0)
            v, face = v_new, face_new
            if not moved:
                break
    with torch.no_grad():
        # quality floor for the next level: never below what relaxation was handed
        out = mesh.with_verts(v)
        bary = barycentric(v, mesh.faces, face, points.to(dt))
    return out, face, bary


def relax_stage(ws: "WorkingSet", cfg: RelaxConfig) -> "WorkingSet":
    """The relaxation stage: the working set on the relaxed mesh, points re-located."""
    if cfg.relax_iterations <= 0:
        return ws
    active = ws.noise <= cfg.relax_noisy * ws.tol
    mesh, face, bary = relax_mesh(ws.mesh, ws.points, ws.point_item, ws.face, cfg, active)
    return ws.replace(mesh=mesh, face=face, bary=bary)
