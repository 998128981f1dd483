"""Print readiness (issue 10): the face clearance between mating cut faces, the bed contact of every piece in its
print orientation, the bed margin, labels on every piece, and the preview's depth buffer."""

import numpy as np
import pytest
import trimesh

from volpuzzle import compose as C
from volpuzzle import geometry as G

from test_compose import CASES, _orientation, _warp  # noqa: E402  (the small analytic models)
from volpuzzle.mapping import Map
from volpuzzle.tile import tile

# ---------------------------------------------------------------------------------------------------------------------
# face clearance


def _pieces(name, clearance):
    make, grid, periodic, seams, tol, warp = CASES[name]
    vol = make()
    t = tile(vol, grid, periodic=periodic, seams=seams)
    fmap = Map(vol, _warp() if warp else None, _orientation(vol))
    sampling = C.sample_parameters(t, fmap, tol)
    return t, sampling, C.compose(t, fmap, [], tol, sampling=sampling, face_clearance=clearance)


@pytest.mark.parametrize("name", ["warped", "twisted", "cone", "pyramid"])
def test_neighbours_are_apart_by_the_face_clearance_and_volumes_add_up(name):
    clearance = 0.3
    t, sampling, plain = _pieces(name, 0.0)
    _, _, gapped = _pieces(name, clearance)
    by_cell = {p.cell: p for p in gapped}
    for p in gapped:
        G.check_solid(p.mesh, p.id)
    for f in t.faces:
        ma, mb = by_cell[f.lower].mesh, by_cell[f.upper].mesh
        a, b = G.from_trimesh(ma, "a"), G.from_trimesh(mb, "b")
        # edges of coarse triangles where a cut face meets a collapsed axis or the outside come a little closer
        assert a.min_gap(b, 5 * clearance) >= 0.75 * clearance, (f.lower, f.upper)
        # the two sides share one triangulation, each vertex moved by half the clearance along the same normals
        _, dist, _ = trimesh.proximity.closest_point(mb, ma.vertices)
        facing = dist[dist < 2 * clearance]
        assert len(facing) > 10
        assert facing.min() >= 0.9 * clearance and np.median(facing) == pytest.approx(clearance, rel=0.02)
    removed = sum(p.volume for p in plain) - sum(p.volume for p in gapped)
    assert removed == pytest.approx(C.face_clearance_volume(sampling, clearance), rel=0.03)


def test_no_clearance_on_a_single_cell():
    make, grid, periodic, seams, tol, warp = CASES["box"]
    vol = make()
    t = tile(vol, (1, 1, 1))
    fmap = Map(vol, None, _orientation(vol))
    sampling = C.sample_parameters(t, fmap, tol)
    plain = C.compose(t, fmap, [], tol, sampling=sampling)
    gapped = C.compose(t, fmap, [], tol, sampling=sampling, face_clearance=0.3)
    assert gapped[0].volume == pytest.approx(plain[0].volume, rel=1e-12)
    assert C.face_clearance_volume(sampling, 0.3) == 0.0


# ---------------------------------------------------------------------------------------------------------------------
# preview


def test_preview_hides_a_box_inside_another(tmp_path):
    from PIL import Image

    from volpuzzle.preview import render_preview

    outer = trimesh.creation.box([20, 20, 20])
    inner = trimesh.creation.box([8, 8, 8])
    red, blue = np.array([230, 30, 30], np.uint8), np.array([30, 30, 230], np.uint8)
    for meshes, colors in (([outer, inner], [red, blue]), ([inner, outer], [blue, red])):
        render_preview(tmp_path / "p.png", meshes, colors, offsets=np.zeros((2, 3)))
        px = np.asarray(Image.open(tmp_path / "p.png").convert("RGB")).astype(int)
        blueish = (px[:, :, 2] > px[:, :, 0] + 60)
        assert not blueish.any()  # whatever the order, no pixel of the hidden box shows
        assert (px[:, :, 0] > px[:, :, 2] + 60).sum() > 1000  # the outer box is there


def test_preview_takes_a_colour_per_triangle_and_draws_a_plate(tmp_path):
    from PIL import Image

    from volpuzzle.preview import render_preview

    box = trimesh.creation.box([20, 20, 20])
    per_tri = np.tile(np.array([[30, 200, 30]], np.uint8), (len(box.faces), 1))
    per_tri[box.face_normals[:, 2] > 0.5] = (200, 30, 200)  # the top painted another colour
    render_preview(tmp_path / "p.png", [box], [per_tri], plate=([box], [per_tri], (60, 50)))
    img = Image.open(tmp_path / "p.png")
    assert img.size == (2400, 800)
    px = np.asarray(img.convert("RGB")).astype(int)
    magenta = (px[:, :, 0] > 120) & (px[:, :, 2] > 120) & (px[:, :, 1] < 80)
    green = (px[:, :, 1] > px[:, :, 0] + 60) & (px[:, :, 1] > px[:, :, 2] + 60)
    for panel in range(3):
        cols = slice(panel * 800, (panel + 1) * 800)
        assert magenta[:, cols].sum() > 200 and green[:, cols].sum() > 200
    grey = ((np.ptp(px, axis=2) < 4) & (px[:, :, 0] > 100) & (px[:, :, 0] < 250))[:, 1600:]
    assert grey.sum() > 1000  # the bed under the plate view
