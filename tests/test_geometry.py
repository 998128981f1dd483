"""geometry: the manifold3d / trimesh bridge raises GeometryError (naming the piece) instead of passing on a failed
status or a broken mesh."""

import manifold3d
import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from volpuzzle import geometry as G
from volpuzzle.check import closed_problem
from volpuzzle.errors import GeometryError


def _cube_mesh():
    return trimesh.creation.box(extents=(2.0, 2.0, 2.0))


def test_round_trip_keeps_volume_and_vertices():
    box = _cube_mesh().subdivide()
    m = G.from_trimesh(box, "p0-0-0")
    back = G.to_trimesh(m)
    assert m.volume() == pytest.approx(8.0)
    assert len(back.vertices) == len(box.vertices)  # grid vertices of flat faces are not merged away
    assert closed_problem(back) is None


def test_not_manifold_names_piece_and_status():
    box = _cube_mesh()
    faces = np.vstack([box.faces, box.faces[:1]])  # one triangle twice: an edge with three triangles
    with pytest.raises(GeometryError, match=r"p1-2-3.*NotManifold"):
        G.manifold_from_mesh(box.vertices, faces, "p1-2-3")


def test_non_finite_vertices_refused():
    box = _cube_mesh()
    v = box.vertices.copy()
    v[0, 0] = np.nan
    with pytest.raises(GeometryError, match="p0-0-1: .*non-finite"):
        G.manifold_from_mesh(v, box.faces, "p0-0-1")


def test_empty_solid_refused():
    with pytest.raises(GeometryError, match="encloses no volume"):
        G.manifold_from_mesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=int), "p0-0-0")


def test_boolean_ops_and_unknown_op():
    a = manifold3d.Manifold.cube((1, 1, 1))
    b = manifold3d.Manifold.cube((1, 1, 1)).translate((0.5, 0.5, 0.5))
    assert G.boolean(a, b, "union", "x").volume() == pytest.approx(1.875)
    assert G.boolean(a, b, "difference", "x").volume() == pytest.approx(0.875)
    assert G.boolean(a, b, "intersection", "x").volume() == pytest.approx(0.125)
    with pytest.raises(GeometryError, match="unknown boolean operation 'xor'"):
        G.boolean(a, b, "xor", "x")


def test_boolean_with_failed_operand_raises():
    # one lone triangle is not a closed surface: the engine marks it NotManifold, and the status must reach the user
    bad = manifold3d.Manifold(manifold3d.Mesh64(vert_properties=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]),
                                                tri_verts=np.array([[0, 1, 2]], dtype=np.uint64)))
    assert bad.status() == manifold3d.Error.NotManifold
    with pytest.raises(GeometryError, match="p9: .*status"):
        G.boolean(manifold3d.Manifold.cube((1, 1, 1)), bad, "union", "p9")


def test_a_batch_boolean_is_the_booleans_one_at_a_time():
    body = manifold3d.Manifold.cube((4, 4, 4))
    pins = [manifold3d.Manifold.cylinder(2.0, 0.5).translate((1, 1, 3)),
            manifold3d.Manifold.cube((1, 1, 1)).translate((3.5, 2, 2))]
    holes = [manifold3d.Manifold.cylinder(2.0, 0.5).translate((3, 1, -0.5)),
             manifold3d.Manifold.cube((1, 1, 1)).translate((-0.5, 2.5, 1))]
    one, batch = body, G.boolean_all(body, pins, "union", "x")
    for p in pins:
        one = G.boolean(one, p, "union", "x")
    assert batch.volume() == pytest.approx(one.volume(), abs=1e-9) and batch.volume() > body.volume()
    one, batch = body, G.boolean_all(body, holes, "difference", "x")
    for h in holes:
        one = G.boolean(one, h, "difference", "x")
    assert batch.volume() == pytest.approx(one.volume(), abs=1e-9) and batch.volume() < body.volume()
    assert G.boolean_all(body, [], "union", "x") is body
    with pytest.raises(GeometryError, match=r"x: unknown batch boolean operation 'intersection' \(expected one of "
                                            r"\['difference', 'union'\]\)"):
        G.boolean_all(body, holes, "intersection", "x")


def test_a_batch_boolean_names_the_operand_that_failed():
    bad = manifold3d.Manifold(manifold3d.Mesh64(vert_properties=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]),
                                                tri_verts=np.array([[0, 1, 2]], dtype=np.uint64)))
    good = manifold3d.Manifold.cube((1, 1, 1))
    with pytest.raises(GeometryError, match=r"p9 \(pins\): the geometry engine failed at union \(operand 3\) "
                                            r"\(status NotManifold\)"):
        G.boolean_all(good, [good.translate((2, 0, 0)), bad], "union", "p9 (pins)")


def test_weld_collapses_a_face_to_a_line():
    # a wedge: the box's x=0 face squeezed onto the z axis, as at a cone's axis
    box = _cube_mesh().subdivide()
    v = box.vertices.copy()
    v[np.isclose(v[:, 0], -1.0), 1] = 0.0
    v[np.isclose(v[:, 0], -1.0), 0] = -1.0
    v2, f2 = G.weld(v, box.faces, 1e-9)
    mesh = trimesh.Trimesh(v2, f2, process=False)
    assert closed_problem(mesh) is None
    assert mesh.volume == pytest.approx(6.0)  # the squeeze reaches only to the next grid plane, x = 0


def test_weld_cancels_coincident_opposite_faces():
    # two unit cubes sharing a face, given as one triangle soup: the inner face pair cancels, leaving one box
    a = trimesh.creation.box(extents=(1, 1, 1))
    # the mirror image across x = 0.5 has the same triangles on that face, in the opposite orientation
    bv = a.vertices * np.array([-1.0, 1.0, 1.0]) + np.array([1.0, 0.0, 0.0])
    v = np.vstack([a.vertices, bv])
    f = np.vstack([a.faces, a.faces[:, [0, 2, 1]] + len(a.vertices)])
    v, f = G.weld(v, f, 1e-9)
    mesh = trimesh.Trimesh(v, f, process=False)
    assert closed_problem(mesh) is None, "pair"
    assert mesh.volume == pytest.approx(2.0)


def test_cylinder_lies_along_its_direction_between_start_and_stop():
    from volpuzzle.geometry import cylinder, to_trimesh

    d = np.array([1.0, 2.0, 2.0]) / 3.0
    c = np.array([5.0, -1.0, 2.0])
    mesh = to_trimesh(cylinder(c, 3 * d, 1.5, -2.0, 4.0, "test", segments=64))
    t = (mesh.vertices - c) @ d
    radial = np.linalg.norm((mesh.vertices - c) - t[:, None] * d, axis=1)
    assert np.allclose([t.min(), t.max()], [-2.0, 4.0]) and np.allclose(radial.max(), 1.5)
    polygon = 0.5 * 64 * np.sin(2 * np.pi / 64) * 1.5**2  # the inscribed 64-gon's area
    assert np.isclose(mesh.volume, 6.0 * polygon)


def test_forget_lets_go_of_the_solids_and_the_derived_arrays_of_a_mesh():
    mesh, other = _cube_mesh(), _cube_mesh().apply_translation([5.0, 0.0, 0.0])
    for m in (mesh, other):
        G.memo(m, "solid", lambda m=m: G.from_trimesh(m, "p"))
        assert m.triangles_center.shape == (12, 3)
    G.forget([mesh])
    assert id(mesh) not in G._MEMO and "triangles" not in mesh._cache and "triangles_center" not in mesh._cache
    # only the meshes named: the other keeps its solid and its arrays, and a forgotten mesh can be judged again
    assert "solid" in G._MEMO[id(other)][2] and "triangles_center" in other._cache
    assert G.memo(mesh, "solid", lambda: G.from_trimesh(mesh, "p")).volume() == pytest.approx(8.0)


def test_freed_memory_goes_back_through_glibc_and_elsewhere_nothing_is_tried(monkeypatch):
    import platform

    G._malloc_trim.cache_clear()
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        assert G._malloc_trim() is not None
    monkeypatch.setattr(G.sys, "platform", "darwin")
    G._malloc_trim.cache_clear()
    assert G._malloc_trim() is None
    G._return_freed_memory()  # a no-op there, not an error
    monkeypatch.undo()
    G._malloc_trim.cache_clear()


def test_a_frame_is_built_with_numpys_cross_products_to_the_bit():
    from volpuzzle.grid import frame_from_direction

    rng = np.random.default_rng(3)
    for n in rng.normal(size=(200, 3)):
        n = n / np.linalg.norm(n)
        e1, e2, _ = frame_from_direction(n)
        helper = np.eye(3)[int(np.argmin(np.abs(n)))]
        expect = np.cross(helper, n)
        expect /= np.linalg.norm(expect)
        assert np.array_equal(e1, expect) and np.array_equal(e2, np.cross(n, expect))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 40), st.integers(0, 40)), max_size=60))
def test_unique_pairs_are_numpys_unique_rows(rows):
    e = np.array(rows, dtype=np.int64).reshape(-1, 2)
    got, counts = G.unique_pairs(e)
    want, want_counts = np.unique(e, axis=0, return_counts=True)
    assert np.array_equal(got, want.reshape(-1, 2)) and np.array_equal(counts, want_counts)


@settings(max_examples=40, deadline=None)
@given(shape=st.sampled_from(["ball", "ring", "torus"]), seed=st.integers(0, 2**16), above=st.floats(0.05, 0.95))
def test_a_section_area_is_the_engines_slice_of_the_same_solid(shape, seed, above):
    # turned any way and cut anywhere through it, with a hole (ring) or two separate islands (a torus cut near its
    # top): the segments' sum is the engine's section area
    mesh = {"ball": lambda: trimesh.creation.icosphere(subdivisions=3, radius=7.0),
            "ring": lambda: trimesh.creation.annulus(r_min=3.0, r_max=6.0, height=4.0, sections=48),
            "torus": lambda: trimesh.creation.torus(major_radius=8.0, minor_radius=2.5)}[shape]()
    rot = trimesh.transformations.random_rotation_matrix(np.random.default_rng(seed).uniform(size=3))
    v = mesh.vertices @ rot[:3, :3].T
    h = float(v[:, 2].min() + above * np.ptp(v[:, 2]))
    want = G.manifold_from_mesh(v, mesh.faces, shape, keep_faces=False).slice(h).area()
    assert G.section_area(v, mesh.faces, h) == pytest.approx(want, rel=1e-6, abs=1e-9)


@pytest.mark.parametrize("parts, heights", [
    ([([4.0, 3.0, 2.0], 0.0)], [-1.0, 0.0, 1.0, 1.5, -1.5]),  # a box cut at its bottom and top faces
    ([([20.0, 20.0, 0.1], 0.05), ([10.0, 10.0, 5.0], 2.5)], [0.1, 0.0]),  # a slab under a post
    ([([10.0, 10.0, 0.1], 0.05), ([20.0, 20.0, 4.9], 2.55)], [0.1, 0.0]),  # a foot under a block
])
def test_a_section_through_vertices_is_the_one_just_above_the_plane_as_the_engines(parts, heights):
    # a face lying in the plane belongs to the part under it: the bed contact is measured FIRST_SLICE_MM above the
    # lowest point, and a step exactly there must read as the engine's slice (and plan_pose's base cut) reads it.
    # parts: boxes (extents, height of the centre), united
    solid = None
    for extents, z in parts:
        box = trimesh.creation.box(extents)
        part = G.manifold_from_mesh(box.vertices + [0.0, 0.0, z], box.faces, "box", keep_faces=False)
        solid = part if solid is None else solid + part
    mesh = G.to_trimesh(solid)
    for h in heights:
        want = solid.slice(h).area()
        assert G.section_area(mesh.vertices, mesh.faces, h) == pytest.approx(want, rel=1e-12, abs=1e-12), h
    if len(parts) == 2:  # the upper part's section, not the step's
        assert G.section_area(mesh.vertices, mesh.faces, 0.1) == pytest.approx(parts[1][0][0] * parts[1][0][1])


