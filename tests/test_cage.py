"""Cages around a mesh: they contain it, are right-handed, and their periodic axes close."""

from pathlib import Path

import numpy as np
import pytest
import trimesh

from volpuzzle.cage import cage_boundary, check_inside, make_cage
from volpuzzle.errors import ModelError
from volpuzzle.io import save_model
from volpuzzle.io.mesh import load_mesh
from volpuzzle.spec import CageSpec, load_spec
from volpuzzle.spline.jacobian import certify_positive

DATA = Path(__file__).parent / "data" / "meshes"
SPECS = Path(__file__).parent.parent / "specs"


@pytest.fixture(scope="module")
def gear():
    return load_mesh(DATA / "stlmodels_gearwheel.bin.stl")


@pytest.fixture(scope="module")
def blob():
    """A tilted ellipsoid: its principal axes are not the world's."""
    m = trimesh.creation.icosphere(2, radius=20)
    m.apply_scale([1.0, 0.5, 0.3])
    m.apply_transform(trimesh.transformations.rotation_matrix(0.5, [1, 1, 0]))
    return m


def det_samples(vol, n=6):
    t = (np.arange(n) + 0.5) / n
    uvw = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3)
    return np.linalg.det(vol.derivatives(uvw))


@pytest.mark.parametrize("kind", ["box", "cylinder", "sphere"])
@pytest.mark.parametrize("which", ["gear", "blob"])
def test_cage_contains_its_mesh_and_is_right_handed(kind, which, request):
    mesh = request.getfixturevalue(which)
    vol, info = make_cage(mesh, CageSpec(type=kind, padding=1.0))
    check_inside(mesh, vol)
    assert np.all(det_samples(vol) > 0)
    assert certify_positive(vol).status in ("proved", "degenerate")  # degenerate: zero only on a collapsed face
    assert info["periodic"] == {"box": [], "cylinder": [1], "sphere": [2]}[kind]


def test_box_uses_the_principal_axes_when_tighter(blob):
    vol, info = make_cage(blob, CageSpec(type="box", padding=0.5))
    assert info["frame"] == "principal axes"
    lo, hi = blob.bounds
    assert np.prod(info["size_mm"]) < np.prod(hi - lo + 1.0)


def test_box_with_control_points_is_still_the_box(blob):
    v1, _ = make_cage(blob, CageSpec(type="box"))
    v3, _ = make_cage(blob, CageSpec(type="box", control_points=(4, 5, 6)))
    assert v3.degrees == (3, 3, 3) and v3.shape == (4, 5, 6)
    uvw = np.random.default_rng(1).random((50, 3))
    assert np.allclose(v1.evaluate(uvw), v3.evaluate(uvw))  # linear precision: same map, more freedom for R


def test_cylinder_of_the_gear_is_around_its_axis(gear):
    vol, info = make_cage(gear, CageSpec(type="cylinder", padding=1.0))
    assert abs(np.dot(info["axis"], [0, 0, 1])) == pytest.approx(1.0)
    assert info["height_mm"] == pytest.approx(10.0)
    # the angle closes exactly: v=0 and v=1 are the same points
    t = np.linspace(0, 1, 5)
    a = vol.evaluate(np.stack([t, np.zeros(5), t], 1))
    b = vol.evaluate(np.stack([t, np.ones(5), t], 1))
    assert np.allclose(a, b)
    # and the circle is exact: constant radius
    rim = vol.evaluate(np.stack([np.ones(64), np.linspace(0, 1, 64), np.zeros(64)], 1))
    r = np.linalg.norm((rim - info["center_mm"])[:, :2], axis=1)
    assert np.ptp(r) < 1e-9 and r[0] == pytest.approx(info["radius_mm"])


def test_sphere_is_exact(blob):
    vol, info = make_cage(blob, CageSpec(type="sphere", padding=1.0))
    uvw = np.random.default_rng(2).random((100, 3))
    uvw[:, 0] = 1.0
    d = np.linalg.norm(vol.evaluate(uvw) - info["center_mm"], axis=1)
    assert np.allclose(d, info["radius_mm"])


@pytest.mark.parametrize("kind", ["box", "cylinder", "sphere"])
def test_boundary_is_closed_and_outward(blob, kind):
    vol, _ = make_cage(blob, CageSpec(type=kind))
    b = cage_boundary(vol)
    assert b.is_watertight and b.is_winding_consistent and b.volume > blob.volume


@pytest.mark.parametrize("kind", ["box", "cylinder", "sphere"])
def test_convex_cage_test_agrees_with_the_boolean(blob, kind):
    """The shortcut for convex cages (the mesh's hull corners inside the boundary's halfspaces) says inside only where
    the Boolean of the whole mesh does, and a mesh moved partly out of the cage is still refused with the distance."""
    from volpuzzle.cage import _inside_convex
    from volpuzzle.geometry import boolean, from_trimesh

    vol, _ = make_cage(blob, CageSpec(type=kind, padding=1.0))
    bnd = cage_boundary(vol)
    assert _inside_convex(blob, bnd)
    outside = boolean(from_trimesh(blob, "blob"), from_trimesh(bnd, "cage"), "difference", "blob outside")
    assert outside.is_empty() or outside.volume() < 1e-9
    moved = blob.copy()
    moved.apply_translation([3.0, 0.0, 0.0])  # 2 mm past a 1 mm padding
    assert not _inside_convex(moved, bnd)
    with pytest.raises(ModelError, match=r"reaches [\d.]+ mm outside"):
        check_inside(moved, vol)


def test_non_convex_cage_is_left_to_the_boolean(blob):
    from volpuzzle.cage import _inside_convex

    # an L of two boxes: the blob's hull corners all lie inside the L's hull, but the blob reaches into the notch
    a = trimesh.creation.box(extents=[60, 20, 20])
    b = trimesh.creation.box(extents=[20, 60, 20])
    b.apply_translation([-20, 20, 0])
    ell = trimesh.boolean.union([a, b], engine="manifold")
    assert not _inside_convex(blob, ell)


def test_mesh_outside_a_nurbs_cage_is_refused_with_the_distance(blob, tmp_path):
    vol, _ = make_cage(blob, CageSpec(type="box", padding=1.0))
    path = tmp_path / "cage.json"
    save_model(vol, path)
    cage, info = make_cage(blob, CageSpec(type="nurbs", nurbs=path, padding=0.0))
    check_inside(blob, cage)
    moved = blob.copy()
    moved.apply_translation(np.asarray(vol.evaluate([[1, 0.5, 0.5]])[0] - vol.evaluate([[0.5, 0.5, 0.5]])[0]) * 0.3)
    with pytest.raises(ModelError, match=r"reaches [\d.]+ mm outside"):
        check_inside(moved, cage)


def test_nurbs_cage_is_scaled_with_the_mesh(blob, tmp_path):
    vol, _ = make_cage(blob, CageSpec(type="box"))
    path = tmp_path / "cage.json"
    save_model(vol, path)
    cage, _ = make_cage(blob, CageSpec(type="nurbs", nurbs=path, padding=0.0), scale=2.0)
    assert np.allclose(cage.control_points, 2 * vol.control_points)


@pytest.mark.parametrize("name", ["bunny-cage", "bunny-sphere", "gear-cylinder"])
def test_mesh_specs_are_valid(name):
    spec = load_spec(SPECS / f"{name}.yaml")
    assert spec.model.mesh is not None and spec.model.mesh.exists()
    assert spec.model.cage is not None
    periodic = {"box": (), "cylinder": (1,), "sphere": (2,)}[spec.model.cage.type]
    assert tuple(spec.periodic) == periodic
