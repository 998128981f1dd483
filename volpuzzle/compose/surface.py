"""A cell's closed surface in mm from the shared face tessellation, its boundary in its own parameters, and the
face clearance: cut faces set back by half of it on each side."""

from typing import NamedTuple

import numpy as np

from .. import geometry
from ..grid import other_axes
from .lattice import seen_back, seen_through
from .sampling import WELD_MM

_FADE = 4.0  # half-clearances over which points inside a face follow the slide of its set-back edge
_LEAN = 0.25  # the least cosine between a point's mean normal and its triangles' that the set-back makes up for
_CAP = 8.0  # half-clearances a point may slide along the outside; where it would need more it moves back instead


class ParameterMesh(NamedTuple):
    """A cell box's boundary in its own parameters: uvw (n, 3); ids (n,) global vertex ids (xyz = sampling.xyz[ids]);
    faces (m, 3) rows of uvw, outward in parameter space; face_bits (n,) int: bit 2a + side set for a point on the
    min (side 0) or max (side 1) face along a."""

    uvw: np.ndarray
    ids: np.ndarray
    faces: np.ndarray
    face_bits: np.ndarray


def cell_box(cell, sampling):
    """The cell's parameter box (2, 3): its min and max corners, exactly the tiling's breaks."""
    return np.array([[sampling.breaks[k][cell.index[k] + s] for k in range(3)] for s in (0, 1)])


def box_face_bits(uvw, box, rel_tol):
    """(n,) int: bit 2a + side set for each point of uvw (n, 3) within rel_tol of the box's size on its min
    (side 0) or max (side 1) face along a."""
    tol = rel_tol * (box[1] - box[0])
    bits = np.zeros(len(uvw), dtype=np.int64)
    for a in range(3):
        bits[np.abs(uvw[:, a] - box[0, a]) <= tol[a]] |= 1 << (2 * a)
        bits[np.abs(uvw[:, a] - box[1, a]) <= tol[a]] |= 1 << (2 * a + 1)
    return bits


def cell_parameter_mesh(cell, sampling):
    """The cell box's boundary in its own parameters, as the faces' tessellation places it -> ParameterMesh."""
    box = cell_box(cell, sampling)
    uvw, ids, tris = [], [], []
    n = 0
    for face in sampling.lattice.cell_faces(tuple(cell.index)):
        a, reverse = face.axis, face.reverse
        fm = sampling.faces[face.key]
        b, c = other_axes(a)
        st = seen_through(np.asarray(fm.st), face.seam)
        q = np.empty((len(st), 3))
        q[:, a] = box[0 if reverse else 1, a]
        q[:, b] = box[0, b] + st[:, 0] * (box[1, b] - box[0, b])
        q[:, c] = box[0, c] + st[:, 1] * (box[1, c] - box[0, c])
        # exact box values on the rectangle's sides, so that the faces meeting at a box edge share their points
        for k, col in ((b, 0), (c, 1)):
            q[st[:, col] == 0.0, k] = box[0, k]
            q[st[:, col] == 1.0, k] = box[1, k]
        uvw.append(q)
        ids.append(fm.ids)
        t = fm.tris[:, [0, 2, 1]] if reverse else fm.tris
        tris.append(t + n)
        n += len(st)
    uvw, ids, tris = np.concatenate(uvw), np.concatenate(ids), np.concatenate(tris)
    # one point per id, unless the id sits at two places of this box (a cell closing on itself across a seam)
    span = box[1] - box[0]
    _, first_of = np.unique(ids, return_index=True)
    ref = uvw[first_of[np.searchsorted(ids[first_of], ids)]]
    far = np.max(np.abs(uvw - ref) / span, axis=1) > 1e-6
    place = np.zeros((len(uvw), 3), dtype=np.int64)
    place[far] = np.round((uvw[far] - box[0]) / span * 2 ** 20).astype(np.int64)
    _, first, inv = np.unique(np.column_stack([ids, place]), axis=0, return_index=True, return_inverse=True)
    inv = inv.ravel()
    uvw, ids, tris = uvw[first], ids[first], inv[tris]
    return ParameterMesh(uvw, ids, tris, box_face_bits(uvw, box, 1e-9))


def _is_cut_face(axis, corner, sampling):
    """The grid face across `axis` at grid vertex `corner` is a cut face, shared with a neighbour, when it is inside
    the grid or on a periodic seam."""
    n = len(sampling.breaks[axis]) - 1
    return 0 < corner[axis] < n or any(s.axis == axis for s in sampling.seams)


def _setback(xyz, faces, slot, cut, half, apex=None):
    """Displacements (n, 3) that set every cut face back by `half` mm along its normal while the cell's outer faces
    stay where they are. xyz (n, 3), faces (m, 3) outward, slot (m,) the cell face (0..5) of each triangle, cut (6,)
    bool. Per point (points closer than WELD_MM count as one: collapsed faces repeat a point under several ids), the
    displacement d is the smallest with d . n_f = -half on each cut face f it lies on and d . n_f = 0 on each outer
    face: a corner of two cut faces moves along both normals, a point where a cut face meets the outside slides
    along the outside, by half / sin(angle) up to _CAP half-clearances; beyond that (or where the constraints are
    nearly parallel) it moves back along its cut faces only. A point then moves further where d leans from one of its
    cut triangles, so that every cut triangle's plane is half back at each corner, and points on a collapsed face
    (a pole) move with the faces meeting there. Points inside one face near its edge then follow the edge's slide
    along the face, fading out over twice the slide (at least _FADE half-clearances), so that none is overtaken by the
    moving edge (a fold) and the tip of a sharp wedge stays half a clearance from the cut.
    Where no move of a point is behind all its cut triangles (an apex where cones meet over more than half a turn,
    the centre of a sphere cage) and `apex` is given, apex(points (k,) indices into xyz, half) -> ApexInset or None
    sets back the points around it through the map (_apex_inset)."""
    from scipy.spatial import cKDTree

    nv = len(xyz)
    cluster = np.arange(nv)
    pairs = cKDTree(xyz).query_pairs(WELD_MM, output_type="ndarray")
    if len(pairs):
        _, cluster = geometry.joined(pairs, nv)
    nc = int(cluster.max()) + 1
    t = xyz[faces]
    cross = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    normals = np.zeros((nc, 6, 3))
    for k in range(3):
        np.add.at(normals, (cluster[faces[:, k]], slot), cross)
    size = np.linalg.norm(normals, axis=2)
    on = size > 1e-12
    unit = np.where(on[..., None], normals / np.maximum(size, 1e-300)[..., None], 0.0)
    _collapsed_take_neighbours(xyz, faces, slot, cluster, on, unit)
    tri_size = np.linalg.norm(cross, axis=1)
    real = tri_size > 1e-12 * max(float(tri_size.max(initial=0.0)), 1e-300)
    target = np.where(on & np.asarray(cut)[None, :], -float(half), 0.0)
    moving = np.flatnonzero(np.any(target != 0.0, axis=1))
    disp = np.zeros((nc, 3))
    if not len(moving):
        return disp[cluster]
    cap = _CAP * half
    d = _least_norm(unit[moving], target[moving])
    # where a cut face meets the outside at a shallow angle (or across a seam or a pole, where the faces' normals are
    # nearly parallel) sliding along the outside would take more than the cap, or the nearly parallel constraints are
    # dropped and the cut face stays: there the point moves back along its cut faces only, and the outside dents (or
    # bulges at a sharp wedge) by at most half the clearance, which no print shows; the gap is kept everywhere
    cut_rows = target[moving] != 0.0
    reached = np.all(~cut_rows | (np.einsum("nij,nj->ni", unit[moving], d) <= 0.99 * target[moving]), axis=1)
    short = reached & (np.linalg.norm(d, axis=1) <= cap)
    if not np.all(short):
        redo = ~short
        d[redo] = _least_norm(unit[moving[redo]] * cut_rows[redo, :, None], target[moving[redo]])
    length = np.linalg.norm(d, axis=1, keepdims=True)
    disp[moving] = d * np.minimum(1.0, cap / np.maximum(length, 1e-300))
    # a cut triangle's plane moves back by d . n_t at each corner, less than half where d leans from n_t (a curved or
    # bumpy face, or a slide along the outside): such a corner moves further, by up to 1 / _LEAN
    on_cut = real & np.asarray(cut)[slot]
    worst = np.full(nc, np.inf)
    for k in range(3):
        c = cluster[faces[on_cut, k]]
        np.minimum.at(worst, c, -np.einsum("ij,ij->i", disp[c], cross[on_cut]) / tri_size[on_cut] / half)
    # where even 1 / _LEAN would not reach some cut triangle's plane, the averaged normals are no guide: the least
    # move behind every triangle is solved instead; where there is none (an apex), `apex` places each id on its own
    override = (np.zeros(0, np.int64), np.zeros((0, 3)))
    apexes = np.zeros(nc, bool)  # clusters whose ids were placed each on its own
    lost = np.flatnonzero(worst < _LEAN)
    if len(lost):
        solved = _behind_every_triangle(disp, lost, cluster, faces, cross, tri_size, real, on_cut, half)
        worst[lost[solved]] = 1.0
        if apex is not None and not solved.all():
            found = apex(np.flatnonzero(np.isin(cluster, lost[~solved])), half)
            if found is not None:
                override = (found.points, found.moves)
                points, placed = override
                for c in np.unique(cluster[points]):  # the slides below follow the mean of the cluster's ids
                    disp[c] = placed[cluster[points] == c].mean(axis=0)
                worst[np.unique(cluster[points])] = 1.0
                apexes[lost[~solved]] = True
        rest = np.flatnonzero(~solved & ~apexes[lost])
        if len(rest):
            # a point where a coarse cut triangle leans far from the mean cut normal cannot get half behind it while
            # staying on the outside (twisted torus at 0.5 mm: 0.017 mm behind, the neighbour's triangle over the
            # same edge came within 0.110 mm): it may move into the outside too, a dent of a fraction of a
            # clearance that no print shows
            inward = _behind_every_triangle(disp, lost[rest], cluster, faces, cross, tri_size, real, on_cut, half,
                                            inward=True)
            worst[lost[rest[inward]]] = 1.0
    disp *= 1.0 / np.clip(worst, _LEAN, 1.0)[:, None]
    # where: clusters on one face only; edges: triangle edges along a line where two faces meet
    pos = np.zeros((nc, 3))
    pos[cluster] = xyz
    count = on.sum(axis=1)
    e = cluster[np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])]
    e = geometry.unique_pairs(np.sort(e, axis=1))[0]
    common = on[e[:, 0]] & on[e[:, 1]]
    e, common = e[common.sum(axis=1) >= 2], common[common.sum(axis=1) >= 2]
    single = np.flatnonzero(count == 1)
    if not len(e) or not len(single):
        return _overridden(disp[cluster], override)
    # a point slid by s along the outside is overtaken by none of the points behind it, and leaves the wedge's tip
    # the half clearance from the cut, when they follow over 2 s (sliding s needs sin(angle) = half / s)
    reach = max(_FADE * half, 2.0 * float(np.linalg.norm(disp, axis=1).max()))
    p0, p1 = pos[e[:, 0]], pos[e[:, 1]]
    seg = p1 - p0
    seg_len2 = np.maximum(np.einsum("ij,ij->i", seg, seg), 1e-300)
    mid = 0.5 * (p0 + p1)
    radius = 0.5 * float(np.sqrt(seg_len2.max())) + reach
    near = cKDTree(mid).query_ball_point(pos[single], radius)
    rows = np.repeat(single, [len(n) for n in near])
    cols = np.fromiter((j for n in near for j in n), dtype=np.int64, count=len(rows))
    face_of = np.argmax(on[rows], axis=1)
    ok = common[cols, face_of]  # the edge bounds the point's own face
    rows, cols, face_of = rows[ok], cols[ok], face_of[ok]
    if not len(rows):
        return _overridden(disp[cluster], override)
    lam = np.clip(np.einsum("ij,ij->i", pos[rows] - p0[cols], seg[cols]) / seg_len2[cols], 0.0, 1.0)
    dist = np.linalg.norm(p0[cols] + lam[:, None] * seg[cols] - pos[rows], axis=1)
    near_edges = (rows, cols, face_of, lam)
    # the nearest edge of each point
    order = np.lexsort((dist, rows))
    rows, cols, face_of, lam, dist = rows[order], cols[order], face_of[order], lam[order], dist[order]
    first = np.r_[True, rows[1:] != rows[:-1]]
    rows, cols, face_of, lam, dist = rows[first], cols[first], face_of[first], lam[first], dist[first]
    # an apex's mean move (its cap's) is no edge's set-back: along an edge from it (a cone's straight ruling, one
    # long segment) the points follow the edge's other end, whose move is the set-back of the same two faces
    lam = np.where(apexes[e[cols, 0]], 1.0, np.where(apexes[e[cols, 1]], 0.0, lam))
    slide = (1.0 - lam)[:, None] * disp[e[cols, 0]] + lam[:, None] * disp[e[cols, 1]]
    n = unit[rows, face_of]
    slide -= np.einsum("ij,ij->i", slide, n)[:, None] * n  # only along the point's own face
    own_reach = np.maximum(_FADE * half, 2.0 * np.linalg.norm(slide, axis=1))
    weight = np.clip(1.0 - dist / own_reach, 0.0, 1.0)
    disp[rows] += weight[:, None] * slide
    _keep_behind_cut_edges(disp, pos, unit, e, common, np.asarray(cut), near_edges, half)
    _back_behind_own_triangles(disp, rows[np.asarray(cut)[face_of]], face_of[np.asarray(cut)[face_of]], unit,
                               cluster, faces, cross, tri_size, on_cut, half)
    return _overridden(disp[cluster], override)


def _back_behind_own_triangles(disp, rows, face_of, unit, cluster, faces, cross, tri_size, on_cut, half):
    """The slide along a cut face is tangent to the point's mean normal, not to its triangles: on a coarse curved face
    it brings a corner in front of a triangle's half set-back plane, and the neighbour's same triangle, slid the other
    way, comes within less than the clearance (0.087 of 0.15 mm on the quarter torus at 0.5 mm). Each slid point
    (rows (k,) clusters, face_of (k,) their cut face) moves back along its face's normal until it is half behind the
    plane of every cut triangle at it again (disp (c, 3) changed in place)."""
    if not len(rows):
        return
    need = np.zeros(len(disp))
    want = np.zeros(len(disp), bool)
    want[rows] = True
    face = np.zeros(len(disp), np.int64)
    face[rows] = face_of
    unit_t = cross / np.maximum(tri_size, 1e-300)[:, None]
    for k in range(3):
        c = cluster[faces[:, k]]
        sel = on_cut & want[c]
        c, n_t = c[sel], unit_t[sel]
        u = unit[c, face[c]]
        cos = np.maximum(np.einsum("ij,ij->i", u, n_t), _LEAN)
        short = (half + np.einsum("ij,ij->i", disp[c], n_t)) / cos  # > 0: less than half behind this triangle
        np.maximum.at(need, c, short)
    move = np.flatnonzero(need > 1e-9 * half)
    disp[move] -= need[move, None] * unit[move, face[move]]


def _overridden(disp, override):
    """disp (n, 3) with the rows of override = (points (k,), displacements (k, 3)) replaced."""
    points, placed = override
    disp[points] = placed
    return disp


def _behind_every_triangle(disp, lost, cluster, faces, cross, tri_size, real, on_cut, half, inward=False):
    """The least displacement of each cluster in `lost` that leaves it `half` behind the plane of every cut triangle
    around it and on the plane of every outer one (with `inward`, on or inside it): a least-distance problem (Lawson &
    Hanson, ch. 23), solved by NNLS.
    disp (c, 3) is changed in place where one exists. -> (len(lost),) bool: solved."""
    from scipy.optimize import nnls

    solved = np.zeros(len(lost), bool)
    where = np.full(len(disp), -1)
    where[lost] = np.arange(len(lost))
    unit_t = cross / np.maximum(tri_size, 1e-300)[:, None]
    rows = [[] for _ in lost]
    for k in range(3):
        w = where[cluster[faces[:, k]]]
        for t in np.flatnonzero((w >= 0) & real):
            rows[w[t]].append(t)
    for i, c in enumerate(lost):
        tris = np.unique(np.asarray(rows[i], dtype=np.int64))
        cut_t, outer_t = tris[on_cut[tris]], tris[~on_cut[tris]]
        # G d >= h: -n . d >= half behind each cut triangle, n . d = 0 on each outer one (as two inequalities)
        outer_g = [-unit_t[outer_t]] if inward else [unit_t[outer_t], -unit_t[outer_t]]
        g = np.concatenate([-unit_t[cut_t]] + outer_g)
        h = np.concatenate([np.full(len(cut_t), float(half)), np.zeros(len(outer_g) * len(outer_t))])
        e = np.vstack([g.T, h[None, :]])
        f = np.array([0.0, 0.0, 0.0, 1.0])
        r = e @ nnls(e, f)[0] - f
        if abs(r[3]) > 1e-9:  # r = 0: the constraints have no common solution
            disp[c] = -r[:3] / r[3]
            solved[i] = True
    return solved


def _keep_behind_cut_edges(disp, pos, unit, e, common, cut, near_edges, half):
    """A point inside one outer face near an edge where a cut face bounds it must end half a clearance behind that
    cut face too, or the neighbour's point just across the cut comes within less: where cells narrow to a pole both
    sides' points sit a fraction of a clearance apart, and fading the edge's slide leaves them short. Each such point
    moves within its own face, away from the cut, by what it lacks (disp (c, 3) changed in place; near_edges:
    candidate (point, edge, own face, position along the edge) rows). Points of a cut face are left to the slide:
    near an apex (a sphere cage's centre) their cut's normal is no guide."""
    rows, cols, own, lam = near_edges
    for c in np.flatnonzero(cut):
        sel = common[cols, c] & ~cut[own]  # points of the outside: a cut face's own are set back already
        if not sel.any():
            continue
        r, k, f, t = rows[sel], cols[sel], own[sel], lam[sel]
        q = pos[e[k, 0]] + t[:, None] * (pos[e[k, 1]] - pos[e[k, 0]])
        nc = (1.0 - t)[:, None] * unit[e[k, 0], c] + t[:, None] * unit[e[k, 1], c]
        nc /= np.maximum(np.linalg.norm(nc, axis=1), 1e-300)[:, None]
        nf = unit[r, f]
        along = nc - np.einsum("ij,ij->i", nc, nf)[:, None] * nf  # the cut's normal within the point's own face
        size = np.linalg.norm(along, axis=1)
        short = np.einsum("ij,ij->i", pos[r] + disp[r] - q, nc) + half  # > 0: less than half behind the cut
        move = (short > 1e-9 * half) & (size > 0.25)  # a cut nearly parallel to the face is the face's own business
        if not move.any():
            continue
        r, along, size, short = r[move], along[move], size[move], short[move]
        step = -(short / size**2)[:, None] * along
        # a point near several edges of the same cut takes the largest move that any of them asks
        order = np.argsort(-np.linalg.norm(step, axis=1), kind="stable")
        r, step = r[order], step[order]
        first = np.unique(r, return_index=True)[1]
        step = step[first]
        length = np.linalg.norm(step, axis=1, keepdims=True)
        # a lack of more than two clearances is no pole's sliver but a wedge's tip or an apex, left to the slide above
        # (moving such points far folds their triangles)
        keep = length[:, 0] <= 4.0 * half
        disp[r[first][keep]] += step[keep]


def _collapsed_take_neighbours(xyz, faces, slot, cluster, on, unit):
    """A collapsed cell face (a pole's line) has no normal, and its own points there would stay while the faces meeting
    along the line move back: the pieces around a pole would still touch along it. Each such point takes every face
    that a point of the line at most one triangle edge away lies on, with that point's normal (on (c, 6), unit (c, 6,
    3) per cluster, changed in place)."""
    from scipy.spatial import cKDTree

    t = xyz[faces]
    area = np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
    per_slot = np.bincount(slot, weights=area, minlength=6)
    flat = per_slot <= 1e-9 * max(float(per_slot.max()), 1e-300)
    if not flat.any():
        return
    line = np.unique(cluster[faces[flat[slot]]])
    spacing = np.zeros(int(cluster.max()) + 1)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        length = np.linalg.norm(t[:, a] - t[:, b], axis=1)
        np.maximum.at(spacing, cluster[faces[:, a]], length)
        np.maximum.at(spacing, cluster[faces[:, b]], length)
    pos = np.zeros((len(spacing), 3))
    pos[cluster] = xyz
    for f in np.flatnonzero(~flat):
        have = line[on[line, f]]
        if not len(have):
            continue
        dist, k = cKDTree(pos[have]).query(pos[line])
        take = (dist <= spacing[line] + 1e-12) & ~on[line, f]
        unit[line[take], f] = unit[have[k[take]], f]
        on[line[take], f] = True


def _least_norm(normals, target):
    """Minimum-norm least-squares d (n, 3) with normals[i] @ d[i] = target[i], batched: normals (n, 6, 3) unit or
    zero rows, target (n, 6); nearly parallel constraints are dropped rather than amplified."""
    return np.einsum("nij,nj->ni", np.linalg.pinv(normals, rcond=0.05), target)


def cell_surface(cell, sampling, fmap, face_clearance=0.0):
    """Closed, outward triangulated boundary of the cell in mm: (vertices (n, 3), faces (m, 3) int). With
    face_clearance > 0 the cut faces are set back by half of it (the neighbour sets its side back by the other
    half), the outer faces stay exact."""
    tri_ids, slots, cut = [], [], np.zeros(6, bool)  # triangles as global vertex ids, their cell face, cut faces
    sides = np.zeros((6, 2), np.int64)  # the axis and side (0 min, 1 max) of each cell face
    for k, face in enumerate(sampling.lattice.cell_faces(tuple(cell.index))):
        fm = sampling.faces[face.key]
        t = fm.ids[fm.tris]
        tri_ids.append(t[:, [0, 2, 1]] if face.reverse else t)
        slots.append(np.full(len(t), k))
        cut[k] = _is_cut_face(face.axis, face.corner, sampling)
        sides[k] = face.axis, 0 if face.reverse else 1
    tri_ids = np.concatenate(tri_ids)
    uniq, faces = np.unique(tri_ids.ravel(), return_inverse=True)
    faces = faces.reshape(-1, 3)
    if fmap.orientation < 0:
        faces = faces[:, [0, 2, 1]]
    xyz = sampling.xyz[uniq]
    if face_clearance > 0 and cut.any():
        slot = np.concatenate(slots)

        insets = []  # the apex's answer, when _setback asks for one: its triangles are split below

        def apex(points, half, xyz=xyz):  # set back through the map, which _setback does not know; rare, so the
            box = cell_box(cell, sampling)  # cell's parameters are gathered only when an apex asks for them
            uvw = _in_box(sampling.uvw[uniq], box, sampling)
            insets.append(_apex_inset(uvw, xyz, faces, slot, sides, cut, box, fmap, points, half))
            return insets[-1]

        half = 0.5 * face_clearance
        xyz = xyz + _setback(xyz, faces, slot, cut, half, apex)
        if insets and insets[-1] is not None:
            xyz, faces = _refine_apex(xyz, faces, cut[slot], insets[-1], fmap, _APEX_SAG * half)
    return geometry.weld(xyz, faces, WELD_MM)


def _in_box(uvw, box, sampling):
    """uvw (n, 3) with each point that lies across a periodic seam from the cell box (2, 3) moved to the seam's other
    face, where the box reaches it: shifted by the period along the seam's axis and, for a seam that swaps or flips
    the face coordinates (a twisted torus), with them mapped as the seam maps them."""
    uvw = np.array(uvw, dtype=float)
    dom = np.asarray(sampling.domain, dtype=float)
    for seam in sampling.seams:
        a = seam.axis
        b, c = other_axes(a)
        lo, span_bc = dom[0, [b, c]], dom[1, [b, c]] - dom[0, [b, c]]
        period = float(dom[1, a] - dom[0, a])
        span = box[1, a] - box[0, a]
        for rows, shift, move in ((uvw[:, a] > box[1, a] + 1e-9 * span, -period, seen_through),
                                  (uvw[:, a] < box[0, a] - 1e-9 * span, period, seen_back)):
            if rows.any() and (seam.swap or any(seam.flip)):  # (an identity seam keeps its coordinates' bits)
                st = (uvw[np.ix_(rows, [b, c])] - lo) / span_bc
                uvw[np.ix_(rows, [b, c])] = lo + move(st, seam) * span_bc
            uvw[rows, a] += shift
    return uvw


class ApexInset(NamedTuple):
    """Points set back through the map round an apex: points (j,) indices into the cell's points, moves (j, 3) mm,
    uvw (j, 3) the cell parameters they were moved to."""

    points: np.ndarray
    moves: np.ndarray
    uvw: np.ndarray


_APEX_SHARE = 0.4  # of a cell's span along each axis that an apex's ids stay inside from a cut face
_APEX_CHORD = 1.25  # half-clearances that each moved apex id keeps from the cut faces, measured along the parameters
_APEX_REACH = 4.0  # the parameter move fades out at this many times the apex's own depth along the collapsed axis
_APEX_SAG = 0.1  # half-clearances that an edge round an apex may bow from the map
_APEX_LEVELS = 5  # times the edges round an apex are halved at most


def _apex_inset(uvw, xyz, faces, slot, sides, cut, box, fmap, points, half):
    """The points around an apex set back through the map, or None: `points` (k,) indices into uvw (n, 3) and xyz
    (n, 3) that sit at one point where a cell face collapses (the centre of a sphere cage, where the cones of the
    polar cuts meet) and that no single move can set back from all of their cut triangles: each cone bends round
    them over more than half a turn. Every id there moves off the collapsed face into the cell along the map, to the
    parameters of its own place on the boundary, clamped inside every cut face (by _APEX_SHARE of the span at most),
    as far along the collapsed axis as keeps it _APEX_CHORD half-clearances from each cut face: the apex becomes a
    small cap and each cone's triangles keep their own direction. The points nearer the apex than _APEX_REACH times
    that depth move the same way, the depth fading out, their other parameters squeezed to keep _APEX_CHORD
    half-clearances inside every cut face. -> ApexInset (the cap's triangles are split later, _refine_apex)."""
    t = xyz[faces]
    area = np.bincount(slot, weights=np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1),
                       minlength=6)
    collapsed = area <= 1e-9 * max(float(area.max()), 1e-300)
    span = box[1] - box[0]
    rel = 1e-9 * span
    down = [k for k in np.flatnonzero(collapsed)
            if np.all(np.abs(uvw[points, sides[k, 0]] - box[sides[k, 1], sides[k, 0]]) <= rel[sides[k, 0]])]
    if len(down) != 1:
        return None  # not one collapsed face under all of them: no axis to move along
    axis, side = sides[down[0]]
    others = [a for a in range(3) if a != axis]
    cut_sides = [(a, sd) for a, sd in sides[cut] if a != axis]
    lo, hi = box[0].copy(), box[1].copy()
    for a, sd in cut_sides:
        if sd == 0:
            lo[a] = box[0, a] + _APEX_SHARE * span[a]
        else:
            hi[a] = box[1, a] - _APEX_SHARE * span[a]
    q = np.clip(uvw[points], lo, hi)
    sign = 1.0 if side == 0 else -1.0
    depth = 1e-4 * span[axis]
    while True:
        if depth > 0.25 * span[axis]:
            return None
        q[:, axis] = box[side, axis] + sign * depth
        moved = fmap.evaluate(q)
        near = []
        for a, sd in cut_sides:
            on_face = q.copy()
            on_face[:, a] = box[sd, a]
            chord = np.linalg.norm(moved - fmap.evaluate(on_face), axis=1)
            # ids on a pole's line (a second collapsed face) lie on every face through it: no distance to keep there
            chord = chord[chord > 1e-9 * max(float(np.abs(moved).max()), 1.0)]
            near.append(float(chord.min()) if len(chord) else np.inf)
        if min(near) >= _APEX_CHORD * half:
            break
        depth *= 1.25
    # every point within the reach: its collapsed parameter pushed in by the fading depth, the others clamped
    reach = _APEX_REACH * depth
    off = sign * (uvw[:, axis] - box[side, axis])
    region = np.flatnonzero(off < reach)
    outer_sides = [(a, sd) for a, sd in sides[~cut & ~collapsed]]
    for a, sd in outer_sides:
        if np.any(np.abs(uvw[region, a] - box[sd, a]) <= rel[a]):
            return None  # an outer face near the apex must stay where it is
    q = uvw[region].copy()
    q[:, axis] = box[side, axis] + sign * (depth + off[region] * (1.0 - depth / reach))
    _, jac = fmap.evaluate_with_jacobian(q)
    lo = np.repeat(box[:1], len(region), axis=0)
    hi = np.repeat(box[1:], len(region), axis=0)
    for a, sd in cut_sides:
        step = np.minimum(_APEX_SHARE * span[a], _APEX_CHORD * half / np.maximum(np.linalg.norm(jac[:, :, a], axis=1),
                                                                                   1e-300))
        if sd == 0:
            lo[:, a] = box[0, a] + step
        else:
            hi[:, a] = box[1, a] - step
    # squeezed into the bounds rather than clamped: the bounds vary from point to point with the map's stretch, and
    # a clamp would put neighbours out of order there (folded triangles), a squeeze keeps their order
    for a in others:
        q[:, a] = lo[:, a] + (uvw[region, a] - box[0, a]) / span[a] * (hi[:, a] - lo[:, a])
    return ApexInset(region, fmap.evaluate(q) - xyz[region], q)


def _refine_apex(xyz, faces, on_cut, inset, fmap, sag):
    """The points round an apex, set back through the map (_apex_inset), with their triangles split until these
    follow it. The ids of a collapsed face sit at one point, so the sampling leaves it as coarse as it comes (a fan, a
    few points over half a turn), and the faces along its edges are fans from that point: moved apart to the apex's
    cap their flat triangles span up to a right angle round the cones' axis, bow through the concave cut face next
    to them (closer to the neighbour than any vertex) and through one another. Each edge between two such points whose
    midpoint lies more than `sag` mm from the map's point of their mean parameters is split there, and every triangle
    along it with it (one split edge: two triangles, two: three, three: four), at most _APEX_LEVELS times. Inside a
    cut face a chord within the cell keeps its depth below the map (the new point moves along the face only): the
    neighbour's side of the face keeps its chords, and the split must not bring this side closer to it; next to the
    cap it follows the map in full, or the kept depth slides it over the cap's edge (crossing triangles). The
    parameters keep the order the cell's own tessellation gave them (_apex_inset squeezes rather than clamps), so the
    finer triangles do not fold. xyz (n, 3) set back, faces (m, 3) outward, on_cut (m,) bool: the triangle lies on a
    cut face. -> (points (k, 3), faces (l, 3)), the first n points those given."""
    par = np.full((len(xyz), 3), np.nan)  # each point's parameters round the apex, where it has them
    par[inset.points] = inset.uvw
    for _ in range(_APEX_LEVELS):
        t = xyz[faces]
        cross = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        e, inv = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1),
                           axis=0, return_inverse=True)
        inv = inv.ravel()
        normal = np.zeros((len(e), 3))  # outward, the sum over the triangles along each edge
        np.add.at(normal, inv, np.tile(cross, (3, 1)))
        normal /= np.maximum(np.linalg.norm(normal, axis=1), 1e-300)[:, None]
        inside_cut = np.ones(len(e), bool)  # every triangle along the edge on a cut face
        np.logical_and.at(inside_cut, inv, np.tile(on_cut, 3))
        on_cap = np.zeros(len(xyz), bool)
        on_cap[faces[~on_cut]] = True
        inside_cut &= ~on_cap[e].any(axis=1)
        moved = np.all(np.isfinite(par[e]), axis=(1, 2))
        e, normal, inside_cut = e[moved], normal[moved], inside_cut[moved]
        if not len(e):
            break
        q = 0.5 * (par[e[:, 0]] + par[e[:, 1]])
        on_map = fmap.evaluate(q)
        bow = 0.5 * (xyz[e[:, 0]] + xyz[e[:, 1]]) - on_map
        depth = np.minimum(np.einsum("ij,ij->i", bow, normal), 0.0) * inside_cut  # the depth a chord keeps
        split = np.linalg.norm(bow - depth[:, None] * normal, axis=1) > sag
        if not split.any():
            break
        new = on_map + depth[:, None] * normal
        e, n = e[split], len(xyz)
        xyz, par = np.vstack([xyz, new[split]]), np.vstack([par, q[split]])
        size = len(xyz)
        key = e[:, 0] * size + e[:, 1]
        order = np.argsort(key)
        key, new_id = key[order], n + order
        mids = np.full(faces.shape, -1)  # the new point on each triangle's edge i -> i + 1, -1 where not split
        for i in range(3):
            a, b = faces[:, i], faces[:, (i + 1) % 3]
            k = np.minimum(a, b) * size + np.maximum(a, b)
            at = np.clip(np.searchsorted(key, k), 0, len(key) - 1)
            mids[:, i] = np.where(key[at] == k, new_id[at], -1)
        keep = np.all(mids < 0, axis=1)
        split_t = np.flatnonzero(~keep)
        parts = [_split_triangle(faces[i], mids[i]) for i in split_t]
        faces = np.vstack([faces[keep]] + [np.array(p) for p in parts])
        on_cut = np.concatenate([on_cut[keep]] + [np.full(len(p), on_cut[i])
                                                  for i, p in zip(split_t, parts, strict=True)])
    return xyz, faces


def _split_triangle(tri, mids):
    """The triangles (k, 3), same orientation, that replace triangle tri (3,) whose edges tri[i]-tri[i+1] are split at
    mids[i] (-1: not split)."""
    a, b, c = (int(x) for x in tri)
    ab, bc, ca = (int(x) for x in mids)
    if ab >= 0 and bc >= 0 and ca >= 0:
        return [[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]
    # rotate so that the split edges come first: (a, b) always split, (b, c) maybe
    for _ in range(3):
        if ab >= 0 and (bc >= 0 or ca < 0):
            break
        a, b, c, ab, bc, ca = b, c, a, bc, ca, ab
    if bc >= 0:
        return [[a, ab, c], [ab, b, bc], [ab, bc, c]]
    return [[a, ab, c], [ab, b, c]]


def face_clearance_volume(sampling, face_clearance):
    """mm^3 that a face clearance takes out of the puzzle: the clearance times the area of every cut face, each
    shared face counted once (corners and edges add terms of order clearance^2 only)."""
    if face_clearance <= 0:
        return 0.0
    area = 0.0
    for key, fm in sampling.faces.items():
        if not _is_cut_face(key.axis, key.corner, sampling):
            continue
        t = sampling.xyz[fm.ids[fm.tris]]
        area += float(0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())
    return face_clearance * area
