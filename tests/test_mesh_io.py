"""Mesh input: every malformed and broken file of tests/data/meshes gets a decision, and refusals name the file."""

from pathlib import Path

import numpy as np
import pytest
import trimesh

from volpuzzle.errors import ModelError
from volpuzzle.io.mesh import load_mesh, load_mesh_scaled

DATA = Path(__file__).parent / "data" / "meshes"
BAD = DATA / "malformed"
BROKEN = DATA / "broken"


def refused(path, *needles, repair=False):
    with pytest.raises(ModelError) as e:
        load_mesh(path, repair=repair)
    msg = str(e.value)
    assert str(path) in msg
    for n in needles:
        assert n in msg, msg
    return msg


def tetra_ok(path):
    m = load_mesh(path)
    assert len(m.faces) == 4 and m.is_watertight
    assert m.volume == pytest.approx(1 / 6)


# --- malformed STL: refused (the file is wrong, nothing sensible can be read) --------------------------------------
def test_empty_file_is_refused():
    refused(BAD / "empty.stl", "empty")


def test_facet_with_four_vertices_is_refused_with_its_line():
    refused(BAD / "fourVertices.ascii.stl", "facet 1 (line 2) has 4 vertices")


def test_quad_facet_is_refused():
    refused(BAD / "quad.ascii.stl", "has 4 vertices", "triangles")


def test_facet_with_two_vertices_is_refused():
    refused(BAD / "twoVertices.ascii.stl", "has 2 vertices")


def test_binary_count_disagreeing_with_size_is_refused():
    # the header claims 66 triangles, the file holds 4: truncated or a wrong counter, we cannot tell which
    refused(BAD / "incorrectFaceCounter.bin.stl", "says 66 triangles", "4 triangles after the header")


def test_missing_face_leaves_an_open_surface():
    refused(BAD / "missingFace.ascii.stl", "3 open (boundary) edges", "model.repair")


def test_single_face_is_not_a_solid_even_repaired():
    refused(BAD / "singleFace.ascii.stl", "3 open (boundary) edges")
    refused(BAD / "singleFace.ascii.stl", "even after repair", "encloses no volume", repair=True)


# --- malformed STL that is still readable: accepted, because the triangles alone define the solid -------------------
def test_missing_endsolid_is_accepted_when_every_facet_is_complete():
    tetra_ok(BAD / "missingEndsolid.ascii.stl")


def test_solid_name_mismatch_is_accepted():
    tetra_ok(BAD / "solidNameMismatch.ascii.stl")


@pytest.mark.parametrize("name", ["missingNormal.ascii.stl", "notANumberNormal.ascii.stl", "wrongNormal.ascii.stl",
                                  "wrongNormals.ascii.stl"])
def test_bad_facet_normals_are_ignored(name):
    # slicers recompute normals from the vertex order; a missing, NaN, zero or wrong normal changes nothing
    tetra_ok(BAD / name)


def test_binary_stl_whose_header_starts_with_solid_is_read_as_binary():
    m = load_mesh(BAD / "wrongHeader.bin.stl")
    assert m.is_watertight and m.volume == pytest.approx(1e6)


def test_truncated_ascii_facet_is_refused(tmp_path):
    text = (BAD / "missingEndsolid.ascii.stl").read_text().splitlines()
    p = tmp_path / "cut.stl"
    p.write_text("\n".join(text[:-3]))
    refused(p, "truncated", "facet 4")


def test_nan_vertex_is_refused(tmp_path):
    p = tmp_path / "nan.stl"
    p.write_text((BAD / "solidNameMismatch.ascii.stl").read_text().replace("vertex 1 0 0", "vertex nan 0 0", 1))
    refused(p, "non-finite vertex")


# --- broken meshes ----------------------------------------------------------------------------------------------------
def test_holes_are_counted_and_located():
    refused(BROKEN / "cgal_elephant-with-holes.off", "1353 open (boundary) edges", "near (")


def test_holes_are_filled_by_repair():
    m = load_mesh(BROKEN / "cgal_elephant-with-holes.off", repair=True)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0 and m.body_count == 1


def test_flipped_faces_are_counted():
    refused(BROKEN / "cgal_cube-shuffled.off", "9 edges where neighbouring triangles are inconsistently oriented")


def test_flipped_faces_are_fixed_by_repair():
    m = load_mesh(BROKEN / "cgal_cube-shuffled.off", repair=True)
    assert m.is_winding_consistent and m.volume == pytest.approx(8.0)


def test_two_bodies_are_refused_even_repaired():
    refused(BROKEN / "trimesh_multibody.stl", "2 separate bodies")
    refused(BROKEN / "trimesh_multibody.stl", "even after repair", "2 separate bodies", repair=True)


def test_triangle_soup_is_refused():
    refused(BROKEN / "trimesh_soup.stl", "300 open (boundary) edges", "100 separate bodies")


def test_inside_out_mesh_is_refused_and_repaired(tmp_path):
    m = trimesh.creation.box((2, 3, 4))
    m.invert()
    p = tmp_path / "inside_out.off"
    m.export(p)
    refused(p, "face inward")
    assert load_mesh(p, repair=True).volume == pytest.approx(24.0)


def test_missing_file_and_bad_extension(tmp_path):
    refused(tmp_path / "nope.stl", "no such file")
    p = tmp_path / "mesh.xyz"
    p.write_text("1 2 3")
    refused(p, "unsupported mesh extension")


def test_garbage_off_is_refused(tmp_path):
    p = tmp_path / "bad.off"
    p.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n")
    refused(p, "truncated")
    p.write_text("PLY\n")
    refused(p, "not an OFF file")


def test_garbage_obj_gives_a_model_error(tmp_path):
    p = tmp_path / "bad.obj"
    p.write_bytes(b"\x00\x01garbage\xff" * 10)
    with pytest.raises(ModelError) as e:
        load_mesh(p)
    assert str(p) in str(e.value)


# --- formats and scaling ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("ext", ["stl", "obj", "ply", "off", "glb", "3mf"])
def test_every_format_round_trips(tmp_path, ext):
    m = trimesh.creation.icosphere(1, radius=10)
    p = tmp_path / f"ball.{ext}"
    if ext == "3mf":
        from volpuzzle.io.threemf import write_3mf

        write_3mf(p, [("ball", m.vertices, m.faces, None, None)])
    else:
        m.export(p)
    got = load_mesh(p)
    assert len(got.faces) == len(m.faces)
    assert got.volume == pytest.approx(m.volume, rel=1e-5)


def test_units_then_size(tmp_path):
    p = tmp_path / "box.stl"
    trimesh.creation.box((1, 2, 4)).export(p)
    m, scale = load_mesh_scaled(p, unit_scale=10.0)
    assert scale == 10.0 and np.allclose(sorted(m.extents), [10, 20, 40])
    m, scale = load_mesh_scaled(p, unit_scale=25.4, size=100)
    assert np.max(m.extents) == pytest.approx(100) and scale == pytest.approx(25.0)


def test_gear_wheel_loads_closed():
    m = load_mesh(DATA / "stlmodels_gearwheel.bin.stl")
    assert m.is_watertight and m.volume > 0
    assert m.extents[2] == pytest.approx(8.0)


# --- dense meshes: simplified within the tolerance, or kept ---------------------------------------------------------
@pytest.fixture(scope="module")
def dense_sphere():
    return trimesh.creation.icosphere(5, radius=20.0)  # 20,480 triangles


def test_dense_mesh_is_simplified_within_the_error_both_ways(dense_sphere):
    from volpuzzle.io.mesh import mesh_problems, simplify_dense

    out, info = simplify_dense(dense_sphere, 0.05, above=5000)
    assert info is not None and len(out.faces) == info["triangles"] <= 5000 and info["triangles_in"] == 20480
    assert mesh_problems(out) == []
    # measured independently (trimesh's exact closest points), both ways
    _, d_in, _ = trimesh.proximity.closest_point(out, dense_sphere.vertices)
    _, d_out, _ = trimesh.proximity.closest_point(dense_sphere, out.vertices)
    assert max(d_in.max(), d_out.max()) <= info["max_deviation_mm"] + 1e-9 <= 0.05 + 1e-9
    assert out.volume == pytest.approx(dense_sphere.volume, rel=1e-2)


def test_dense_mesh_is_kept_when_simplifying_would_stray_or_it_is_not_dense(dense_sphere):
    from volpuzzle.io.mesh import simplify_dense

    out, info = simplify_dense(dense_sphere, 1e-6, above=5000)  # no simplification stays within a nanometre
    assert out is dense_sphere and info is None
    out, info = simplify_dense(dense_sphere, 0.05, above=len(dense_sphere.faces))
    assert out is dense_sphere and info is None


def test_far_point_bound_is_exact_where_it_exceeds_enough():
    from volpuzzle.io.mesh import _farthest_from

    # one big triangle beside many small ones: a point over the big one's corner region is far from its centre
    big = trimesh.Trimesh([[0, 0, 0], [100, 0, 0], [0, 100, 0]], [[0, 1, 2]], process=False)
    small = trimesh.creation.icosphere(3, radius=1.0).apply_translation([80, 2, 4])  # centres nearer p
    both = trimesh.util.concatenate([big, small])
    p = np.array([[95.0, 2.0, 0.5]])
    assert _farthest_from(p, both, enough=0.1, k=1) == pytest.approx(0.5)


def test_point_triangle_kernel_matches_trimesh_and_handles_collapsed_triangles():
    from volpuzzle.io._mesh_distance import nearest_distances

    rng = np.random.default_rng(3)
    n = 4000
    tri = rng.normal(size=(n, 3, 3))
    tri[:400, 1] = tri[:400, 0]  # a == b: the segment ac
    tri[400:800] = tri[400:800, :1]  # a point
    tri[800:1200, 2] = tri[800:1200, 0] + (tri[800:1200, 1] - tri[800:1200, 0]) / 3  # collinear: the segment ab
    p = rng.normal(size=(n, 3)) * 2
    v, f = tri.reshape(-1, 3), np.arange(3 * n).reshape(n, 3)  # the kernel reads triangles through their vertices
    got = nearest_distances(p, v, f, np.arange(n)[:, None])
    # reference: dense samples of each collapsed triangle's segment, trimesh's closest point on the rest
    ref = np.linalg.norm(p - trimesh.triangles.closest_point(tri, p), axis=1)
    s = np.linspace(0.0, 1.0, 20001)[None, :, None]
    for lo, hi, a, b in ((0, 400, 0, 2), (800, 1200, 0, 1)):
        seg = tri[lo:hi, a, None] + s * (tri[lo:hi, b, None] - tri[lo:hi, a, None])
        ref[lo:hi] = np.linalg.norm(seg - p[lo:hi, None], axis=2).min(axis=1)
    ref[400:800] = np.linalg.norm(p[400:800] - tri[400:800, 0], axis=1)
    assert np.all(got <= ref + 1e-9) and np.allclose(got, ref, atol=1e-6)
    # the minimum over several candidates per point, starting from a given bound
    near = rng.integers(0, n, size=(n, 5))
    want = np.minimum(0.5, np.min([nearest_distances(p, v, f, near[:, [j]]) for j in range(5)], axis=0))
    assert np.array_equal(nearest_distances(p, v, f, near, np.full(n, 0.5)), want)


def test_load_reports_a_simplified_mesh(dense_sphere, tmp_path, monkeypatch):
    import volpuzzle.io.mesh as iomesh
    from volpuzzle.load import load_model_for
    from volpuzzle.spec import load_spec

    dense_sphere.export(tmp_path / "ball.stl")
    (tmp_path / "ball.yaml").write_text("name: ball\nmodel:\n  mesh: ball.stl\n  cage: {type: box, padding: 2}\n"
                                        "grid: [2, 1, 1]\noutput:\n  tolerance: 0.2\n")
    monkeypatch.setattr(iomesh, "DENSE_TRIANGLES", 5000)
    model = load_model_for(load_spec(tmp_path / "ball.yaml"))
    info = model.info["mesh_simplified"]
    assert info["triangles_in"] == 20480 and model.info["mesh_triangles"] == info["triangles"] <= 5000
    assert info["max_deviation_mm"] <= 0.05
    assert len(model.mesh.faces) == info["triangles"]
