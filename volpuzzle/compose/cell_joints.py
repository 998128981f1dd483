"""A cell's pins and holes: solids in mm united and subtracted on its body, or Booleans in the domain on its own
tessellated parameter box, mapped through F and refined where the new edges bend."""

from typing import NamedTuple

import numpy as np

from .. import geometry
from ..grid import other_axes
from .sampling import SAFETY, WELD_MM
from .surface import box_face_bits, cell_box, cell_parameter_mesh


class CellJoints(NamedTuple):
    """A cell's joint solids (Manifold lists): pins and holes in mm, and domain_pins and domain_holes in the
    parameters of its box (joints with space 'domain')."""

    pins: list
    holes: list
    domain_pins: list
    domain_holes: list


def joint_solids(joints, index):
    """The joint solids of cell `index`, from volpuzzle.joint's Joints -> CellJoints."""
    solids = CellJoints([], [], [], [])
    if not joints:
        return solids
    from .. import joint as joint_mod  # a later stage's helpers; imported only when there are joints

    for j in joints:
        if j.style == "none":
            continue
        domain = j.space == "domain"
        pin_cell, hole_cell = tuple(j.pin_cell), tuple(j.hole_cell)
        if j.style == "pin" and pin_cell == index:
            if domain:
                solids.domain_pins.append(joint_mod.pin_solid_domain(j))
            else:
                solids.pins.append(joint_mod.pin_solid(j))
        if hole_cell == index or (j.style == "dowel" and pin_cell == index):
            if domain:
                solids.domain_holes.append(joint_mod.hole_solid_domain(j, index))
            else:
                solids.holes.append(joint_mod.hole_solid(j, index))
    return solids


def apply_joints(body, pins, holes, what):
    """body (Manifold) with the pins united and the holes subtracted: a cell's pins keep a wall between them, and so
    do its holes, so each kind goes in one batch Boolean (at 1024 pieces 3.6 s of Booleans one at a time, 2.5 s)."""
    if pins:
        body = geometry.boolean_all(body, pins, "union", f"{what} (pins)")
    if holes:
        body = geometry.boolean_all(body, holes, "difference", f"{what} (holes)")
    return body


def _wrap(uvw, sampling):
    """Parameters beyond a periodic face (a pin that crosses the seam) -> the same points on the other side."""
    uvw = np.array(uvw, dtype=float, copy=True)
    lo, hi = sampling.domain
    for a, swap, flip in sampling.seams:
        b, c = other_axes(a)
        span = hi[a] - lo[a]
        for sign in (1, -1):
            out = uvw[:, a] > hi[a] if sign > 0 else uvw[:, a] < lo[a]
            if not np.any(out):
                continue
            st = (uvw[out][:, [b, c]] - lo[[b, c]]) / (hi[[b, c]] - lo[[b, c]])
            if sign > 0:  # max side -> min side: swap, then flip
                st = st[:, ::-1] if swap else st
                st = np.where(np.array(flip), 1.0 - st, st)
            else:  # min side -> max side: unflip, then unswap
                st = np.where(np.array(flip), 1.0 - st, st)
                st = st[:, ::-1] if swap else st
            moved = uvw[out]
            moved[:, [b, c]] = lo[[b, c]] + st * (hi[[b, c]] - lo[[b, c]])
            moved[:, a] -= sign * span
            uvw[out] = moved
    return uvw


def _on_face_positions(q, todo, face_bit, box, xyz_all):
    """Points q[todo] on one face of the cell's ParameterMesh `box` -> their positions on the face's tessellation
    (piecewise linear in its parameters), so that a face cut by a domain pin or hole still lies exactly on the cut
    surface the neighbour sees. xyz_all: sampling.xyz."""
    uvw, ids, tris = box.uvw, box.ids, box.faces
    a = face_bit // 2
    b, c = other_axes(a)
    on = (box.face_bits & (1 << face_bit)) != 0
    ft = tris[np.all(on[tris], axis=1)]
    p = q[todo][:, [b, c]]
    t0, t1, t2 = (uvw[ft[:, k]][:, [b, c]] for k in range(3))
    d1, d2 = t1 - t0, t2 - t0
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    out = np.empty((len(p), 3))
    for i0 in range(0, len(p), 256):
        pp = p[i0:i0 + 256, None, :] - t0[None]
        l1 = (pp[..., 0] * d2[:, 1] - pp[..., 1] * d2[:, 0]) / det
        l2 = (d1[:, 0] * pp[..., 1] - d1[:, 1] * pp[..., 0]) / det
        l0 = 1.0 - l1 - l2
        worst = np.minimum(np.minimum(l0, l1), l2)  # >= 0 inside; the largest is the containing triangle
        k = np.argmax(worst, axis=1)
        r = np.arange(len(k))
        lam = np.clip(np.stack([l0[r, k], l1[r, k], l2[r, k]], 1), 0.0, 1.0)
        lam /= lam.sum(axis=1, keepdims=True)
        out[i0:i0 + 256] = np.einsum("nk,nkd->nd", lam, xyz_all[ids[ft[k]]])
    return out


def domain_body(cell, sampling, fmap, domain_pins, domain_holes, what):
    """Booleans in parameter space on the cell's own tessellated box, then the vertices mapped through F with the
    new triangles off the box faces split until their edges meet the tolerance. -> (vertices, faces) in mm, outward."""
    box_mesh = cell_parameter_mesh(cell, sampling)
    body = geometry.manifold_from_mesh(box_mesh.uvw, box_mesh.faces, f"{what} (parameter box)")
    body = apply_joints(body, domain_pins, domain_holes, f"{what} (in the domain)")
    out = geometry.to_trimesh(body)
    uvw = np.asarray(out.vertices, dtype=float)
    faces = np.asarray(out.faces, dtype=np.int64)
    face_bits = box_face_bits(uvw, cell_box(cell, sampling), 1e-10)  # which box faces each vertex lies on
    xyz = np.full(uvw.shape, np.nan)
    # the box's own points keep their exact parameters through the engine, and take the shared positions
    where = {p.tobytes(): i for p, i in zip(box_mesh.uvw, box_mesh.ids, strict=True)}
    for r in np.flatnonzero(face_bits):
        i = where.get(uvw[r].tobytes())
        if i is not None:
            xyz[r] = sampling.xyz[i]
    for bit in range(6):
        todo = ((face_bits & (1 << bit)) != 0) & np.isnan(xyz[:, 0])
        if np.any(todo):
            xyz[todo] = _on_face_positions(uvw, todo, bit, box_mesh, sampling.xyz)
    off = np.isnan(xyz[:, 0])
    if np.any(off):
        xyz[off] = fmap.evaluate(_wrap(uvw[off], sampling))
    uvw, xyz, faces = _refine(uvw, xyz, faces, face_bits, lambda x: fmap.evaluate(_wrap(x, sampling)),
                              SAFETY * sampling.tolerance)
    if fmap.orientation < 0:
        faces = faces[:, [0, 2, 1]]
    return geometry.weld(xyz, faces, WELD_MM)


def _refine(q, xyz, f, mask, evaluate, target):
    """Split edges whose mapped midpoint is farther than target from the chord, at most one per triangle per pass.
    Edges with both ends on one box face (mask bits in common) lie in the flat, already fitted face and stay."""
    q, xyz, f, mask = np.array(q, dtype=float), np.array(xyz, dtype=float), f.copy(), np.array(mask)
    for _ in range(30):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        edges = geometry.unique_pairs(edges)[0]
        cand = edges[(mask[edges[:, 0]] & mask[edges[:, 1]]) == 0]  # the edges that may bend
        if len(cand) == 0:
            break
        mid = 0.5 * (q[cand[:, 0]] + q[cand[:, 1]])
        xm = evaluate(mid)
        err = np.linalg.norm(xm - 0.5 * (xyz[cand[:, 0]] + xyz[cand[:, 1]]), axis=1)
        bad = np.flatnonzero(err > target)
        if len(bad) == 0:
            break
        tri_of_edge = {}
        for t, tri in enumerate(f):
            for k in range(3):
                u, v = tri[k], tri[(k + 1) % 3]
                tri_of_edge.setdefault((min(u, v), max(u, v)), []).append((t, k))
        used = np.zeros(len(f), dtype=bool)
        new_q, new_x, new_f = [], [], []
        n0 = len(q)
        for i in bad[np.argsort(-err[bad])]:
            u, v = cand[i]
            adj = tri_of_edge.get((u, v), [])
            if any(used[t] for t, _ in adj):
                continue
            m = n0 + len(new_q)
            new_q.append(mid[i])
            new_x.append(xm[i])
            for t, k in adj:
                used[t] = True
                a, b, c = f[t, k], f[t, (k + 1) % 3], f[t, (k + 2) % 3]
                new_f.append((a, m, c))
                new_f.append((m, b, c))
        q = np.concatenate([q, np.array(new_q)])
        xyz = np.concatenate([xyz, np.array(new_x)])
        mask = np.concatenate([mask, np.zeros(len(new_q), dtype=mask.dtype)])
        f = np.concatenate([f[~used], np.array(new_f, dtype=np.int64).reshape(-1, 3)])
    return q, xyz, f
