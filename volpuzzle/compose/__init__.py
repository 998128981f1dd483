"""compose: turn every cell of the tiling into a closed solid in mm, through the map F = M o R, with its joints.

The cell boxes' boundaries are tessellated once for the whole tiling, adaptively per face, in one global vertex table:
  1. grid vertices (the cells' corners);
  2. on every grid edge, 1D samples bisected until F's chord error meets the tolerance;
  3. on every grid face, a 2D triangulation of its parameter rectangle whose boundary is exactly its four edges'
     samples: one Delaunay triangulation of the boundary and a coarse seed (on the face's parameters scaled to mm),
     then longest-edge bisection of every triangle that misses F, until every triangle meets the tolerance.
The tolerance bounds the distance across the surface (from F at a triangle's centroid, edge midpoints and random
points to the triangle's plane; for edges, to the chord): a slide along the surface is a change of parameter, not of
shape, and counting it (as a tensor grid must) multiplied the triangles.
Each vertex is evaluated once and every face is triangulated once, so the two cells on a shared face (also across a
periodic seam, where the min face is the max face seen through the seam map) use the same vertex ids and the same
triangles: neighbours meet on one cut surface, bit for bit. A cell's surface is its six face meshes, oriented outward.

The modules, in the order the data flows:
  lattice      grid vertices, edges and faces, and their canonical keys across periodic seams
  sampling     Sampling: the edges' samples, then every face's triangulation, in one global vertex table
  triangulate  one face's triangulation between its edges' samples, refined until it meets the tolerance
  surface      a cell's closed surface in mm (and its boundary in parameters), cut faces set back by a clearance
  cell_joints  a cell's pins and holes, in mm or as Booleans in the domain mapped through F
  piece        one cell -> Piece
  pool         pieces built by this process and spawned workers together
  stage        compose(): every cell -> Piece, serially or on the pool
"""

from .piece import Piece, build_piece
from .sampling import FaceMesh, Sampling, sample_parameters
from .stage import Pieces, compose
from .surface import cell_parameter_mesh, cell_surface, face_clearance_volume

__all__ = ["FaceMesh", "Piece", "Pieces", "Sampling", "build_piece", "cell_parameter_mesh", "cell_surface",
           "compose", "face_clearance_volume", "sample_parameters"]
