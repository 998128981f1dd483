"""One cell -> Piece: its body through F, the joints, and the check that it is one closed solid."""

from dataclasses import dataclass

import trimesh

from .. import geometry
from ..errors import GeometryError
from .cell_joints import apply_joints, domain_body, joint_solids
from .surface import cell_surface


@dataclass(frozen=True, eq=False)
class Piece:
    """id 'pi-j-k'; cell index; mesh in mm (closed, outward normals); volume and body_volume (before joints) in mm^3."""

    id: str
    cell: tuple
    mesh: trimesh.Trimesh
    volume: float
    body_volume: float
    triangles: int


def build_piece(cell, sampling, fmap, joints, face_clearance=0.0, surface=None):
    """One cell -> Piece: its body through F, cut faces set back by face_clearance / 2, pins united and holes
    subtracted (in mm, or in the domain for joints with space 'domain'); checked to be one closed solid with outward
    normals. surface: the cell's cell_surface (vertices, faces) when it was made already (compose.ahead)."""
    what = cell.id
    index = tuple(cell.index)
    verts, faces = surface if surface is not None else cell_surface(cell, sampling, fmap, face_clearance=face_clearance)
    body = geometry.manifold_from_mesh(verts, faces, what)
    body_volume = float(body.volume())
    solids = joint_solids(joints, index)
    if solids.domain_pins or solids.domain_holes:
        mapped_xyz, mapped_faces = domain_body(cell, sampling, fmap, solids.domain_pins, solids.domain_holes, what)
        body = geometry.manifold_from_mesh(mapped_xyz, mapped_faces, f"{what} (mapped from the domain)")
    body = apply_joints(body, solids.pins, solids.holes, what)
    parts = body.decompose()
    if len(parts) != 1:
        raise GeometryError(f"{what}: the piece falls apart into {len(parts)} bodies after its joints "
                            f"(expected one; a hole may cut through a thin piece: use a smaller joints.radius "
                            f"or joints.length)")
    # No trimesh closed test here: a solid the engine made with no error status (every step above checks it) is a
    # closed, consistently wound, outward 2-manifold by the engine's own guarantee, and it is one non-empty body
    # (above). Asking trimesh the same of its mesh cost ~9 ms a piece, and its caches were not kept (the pool
    # rebuilds the mesh from the arrays); the check stage still judges every piece from its written float32 mesh.
    mesh = geometry.to_trimesh(body)
    return Piece(what, index, mesh, float(body.volume()), body_volume, int(len(mesh.faces)))
