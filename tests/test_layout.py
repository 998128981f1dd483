"""layout and preview: print orientation, plates that hold every piece once, the preview picture."""

import numpy as np
import pytest
import trimesh
from helpers_build import write_spec
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

import volpuzzle
from volpuzzle.errors import SpecError
from volpuzzle.io.threemf import read_3mf
from volpuzzle.layout import layout, print_orientation
from volpuzzle.preview import render_preview


def _wedge():
    """A triangular prism, 40 x 10 x 20: its largest flat face is the slanted one."""
    return trimesh.convex.convex_hull(
        np.array([[0, 0, 0], [40, 0, 0], [0, 10, 0], [0, 0, 20], [40, 0, 20], [0, 10, 20]], float))


def test_a_large_flat_face_goes_down():
    box = trimesh.creation.box([10, 30, 50])
    rot = print_orientation(box)
    placed = box.copy().apply_transform(rot)
    # the 30 x 50 face rests on the plate: the piece stands 10 mm tall
    assert np.isclose(np.ptp(placed.vertices[:, 2]), 10.0)
    wedge = _wedge()
    placed = wedge.copy().apply_transform(print_orientation(wedge))
    down = placed.face_normals[:, 2] < -0.999
    assert placed.area_faces[down].sum() == pytest.approx(max(wedge.facets_area), rel=1e-6)


def test_pins_pointing_down_are_avoided():
    box = trimesh.creation.box([20, 20, 20])  # every face is equally good: the pin decides
    rot = print_orientation(box, [np.array([0.0, 0.0, -1.0])])
    pin_after = rot[:3, :3] @ np.array([0.0, 0.0, -1.0])
    assert pin_after[2] > -0.5


def _half_shell_with_a_pin():
    """A half spherical shell (radii 40 and 34 mm), its ring of a cut face up at z = 0, with a 3 mm pin standing
    2.5 mm up from the ring: a half of the sphere-shell builtin cut in two."""
    import manifold3d

    ball = manifold3d.Manifold.sphere
    shell = (ball(40.0, 128) - ball(34.0, 128)).trim_by_plane((0.0, 0.0, -1.0), 0.0)
    solid = shell + manifold3d.Manifold.cylinder(3.0, 1.5, 1.5, 48).translate((37.0, 0.0, -0.5))
    out = solid.to_mesh()
    return trimesh.Trimesh(np.asarray(out.vert_properties)[:, :3], np.asarray(out.tri_verts), process=True)


def test_a_piece_never_stands_on_its_pin_even_where_its_only_flat_face_holds_it():
    from volpuzzle.layout import plan_pose

    # the ring is the one flat face, but the pin stands on it: the dome goes down, on a base cut, and the pin up
    pose = plan_pose(_half_shell_with_a_pin(), [np.array([0.0, 0.0, 1.0])], pin_tips=[(np.array([37.0, 0, 2.5]), 1.5)])
    assert pose.pins_down == 0 and pose.pins_up == 1
    assert pose.down[2] < -0.99 and pose.base_cut_mm > 0


@pytest.mark.slow
def test_a_build_whose_pin_a_base_cut_shaved_fails_as_its_check_would(tmp_path, monkeypatch):
    import volpuzzle.layout as layout

    plan_pose = layout.plan_pose

    def pin_into_the_bed(mesh, pin_directions=(), hole_openings=(), down=None, **_tips):
        return plan_pose(mesh, pin_directions, hole_openings, down=pin_directions[0] if len(pin_directions) else down)

    monkeypatch.setattr(layout, "plan_pose", pin_into_the_bed)
    spec = write_spec(tmp_path, {"name": "ss", "model": {"builtin": {"type": "sphere-shell"}, "size": 80},
                                 "grid": [1, 2, 1], "output": {"tolerance": 0.5, "labels": False}})
    with pytest.raises(volpuzzle.errors.VolpuzzleError, match=r"the pin of p0-0-0 is missing"):
        volpuzzle.build(spec, output_dir=tmp_path / "out", jobs=1)
    assert not (tmp_path / "out").exists()


def test_every_part_on_exactly_one_plate_inside_it_and_apart():
    rng = np.random.default_rng(3)
    parts = [(f"p{i}", trimesh.creation.box(rng.uniform(15, 60, 3))) for i in range(14)]
    plate, spacing = (120.0, 100.0), 4.0
    placements, plates = layout(parts, plate, spacing)
    names = [n for pl in plates for n in pl.names]
    assert sorted(names) == sorted(n for n, _ in parts)  # every part once
    meshes = dict(parts)
    by_plate = {}
    for pl in placements:
        m = meshes[pl.name].copy().apply_transform(pl.transform)
        lo, hi = m.bounds
        assert lo[2] == pytest.approx(0.0, abs=1e-9)  # resting on the plate
        assert np.all(lo[:2] >= -1e-6) and hi[0] <= plate[0] + 1e-6 and hi[1] <= plate[1] + 1e-6
        assert np.linalg.det(pl.transform[:3, :3]) > 0  # never a mirror image
        by_plate.setdefault(pl.plate, []).append((lo, hi))
    for boxes in by_plate.values():
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                (a0, a1), (b0, b1) = boxes[i], boxes[j]
                gap = np.maximum(b0[:2] - a1[:2], a0[:2] - b1[:2]).max()
                assert gap >= spacing - 1e-6
    assert 0 < min(p.fill_ratio for p in plates) and max(p.fill_ratio for p in plates) <= 1


def test_a_part_larger_than_the_plate_is_refused_with_the_size_needed():
    with pytest.raises(SpecError, match=r"output.plate: .*expected at least \[80.0, 50.0\]"):
        layout([("big", trimesh.creation.box([80, 50, 10]))], (60, 60), 4)


def test_preview_is_a_wide_picture(tmp_path):
    meshes = [trimesh.creation.box([10, 10, 10]).apply_translation([12 * i, 0, 0]) for i in range(3)]
    colors = np.array([[200, 60, 60], [60, 200, 60], [60, 60, 200]], np.uint8)
    render_preview(tmp_path / "p.png", meshes, colors, title="t")
    img = Image.open(tmp_path / "p.png")
    assert img.size == (1600, 800)
    px = np.asarray(img.convert("RGB")).reshape(-1, 3)
    assert (np.abs(px.astype(int) - [200, 60, 60]).sum(1) < 120).any()  # the pieces' colours are in it


@pytest.mark.slow
def test_preview_paints_the_nearer_piece_over_the_farther(tmp_path):
    from volpuzzle.preview import _view_axes

    _, _, eye = _view_axes()
    near = trimesh.creation.box([10, 10, 10])
    far = trimesh.creation.box([10, 10, 10]).apply_translation(-40 * eye)  # straight behind it, seen from the eye
    colors = np.array([[220, 40, 40], [40, 40, 220]], np.uint8)
    for order in ([near, far], [far, near]):
        cols = colors if order[0] is near else colors[::-1]
        render_preview(tmp_path / "p.png", order, cols)
        px = np.asarray(Image.open(tmp_path / "p.png").convert("RGB")).astype(int)
        centre = px[px.shape[0] // 2 - 40:px.shape[0] // 2 + 40, 360:440].reshape(-1, 3)
        assert (centre[:, 0] > centre[:, 2] + 40).mean() > 0.9  # red in front, whatever the drawing order
        assert (px[:5, :5] == 255).all()  # white background


@pytest.mark.slow
def test_build_writes_plates_every_piece_once_and_strict_3mf(tmp_path):
    spec = write_spec(tmp_path, {"name": "plates", "model": {"builtin": {"type": "quarter-torus"}},
                                 "grid": [2, 1, 2], "output": {"directory": str(tmp_path / "out"),
                                                               "tolerance": 0.3, "plate": [90, 80]}})
    report = volpuzzle.build(spec, jobs=1)
    on_plates = [n for pl in report["plates"] for n in pl["pieces"]]
    assert sorted(on_plates) == sorted(p["id"] for p in report["pieces"])
    for pl in report["plates"]:
        objects = read_3mf(tmp_path / "out" / pl["file"], strict=True)
        assert [o[0] for o in objects] == pl["pieces"]
        for _, v, _, rgb in objects:
            assert v[:, 2].min() == pytest.approx(0.0, abs=1e-4)
            assert rgb is not None
    assert (tmp_path / "out" / "preview.png").exists()


def test_plate_smaller_than_the_largest_piece_is_refused_before_building(tmp_path):
    spec = write_spec(tmp_path, {"name": "tiny", "model": {"builtin": {"type": "quarter-torus"}}, "grid": [1, 1, 1],
                                 "output": {"directory": str(tmp_path / "out"), "plate": [30, 30]}})
    with pytest.raises(SpecError, match=r"output.plate: the largest piece needs"):
        volpuzzle.build(spec, jobs=1)
    assert not (tmp_path / "out").exists()


def test_pin_triangles_cover_the_pin_and_nothing_else():
    from types import SimpleNamespace

    import manifold3d

    from volpuzzle.compose import Piece
    from volpuzzle.export import pin_triangles
    from volpuzzle.geometry import to_trimesh

    r, length = 2.0, 6.0
    body = manifold3d.Manifold.cube([20, 20, 20]) + manifold3d.Manifold.cylinder(length + 1, r, r, 96).translate(
        [10, 10, 19])
    mesh = to_trimesh(body)
    piece = Piece("p0-0-0", (0, 0, 0), mesh, float(mesh.volume), float(mesh.volume), len(mesh.faces))
    joint = SimpleNamespace(style="pin", shape="cylinder", pin_cell=(0, 0, 0), hole_cell=(0, 0, 1),
                            center=np.array([10.0, 10.0, 20.0]),
                            direction=np.array([0.0, 0.0, 1.0]), radius=r, length=length)
    mesh._cache.clear()
    flags = pin_triangles([piece], [joint])["p0-0-0"]
    # the look-up leaves no (m, 3, 3) triangles cached on the piece, which the export would carry for every piece
    assert "triangles" not in mesh._cache and "triangles_center" not in mesh._cache
    area = mesh.area_faces[flags.astype(bool)].sum()
    assert area == pytest.approx(2 * np.pi * r * length + np.pi * r * r, rel=0.02)  # side and tip, not the cube
    assert pin_triangles([piece], [SimpleNamespace(**{**vars(joint), "pin_cell": (1, 0, 0)})]) == {}
    # among many pieces and joints, each piece gets its own pins' triangles: a pin of another cell and a dowel of its
    # own cell change nothing
    other = Piece("p1-0-0", (1, 0, 0), mesh, float(mesh.volume), float(mesh.volume), len(mesh.faces))
    many = [SimpleNamespace(**{**vars(joint), "pin_cell": (1, 0, 0), "center": np.array([0.0, 0.0, -50.0])}),
            SimpleNamespace(**{**vars(joint), "style": "dowel"}), joint]
    both = pin_triangles([other, piece], many)
    assert np.array_equal(both["p0-0-0"], flags) and not both["p1-0-0"].any()


@pytest.mark.slow
def test_3mf_pieces_with_a_pin_material_read_back_strictly(tmp_path):
    spec = write_spec(tmp_path, {"name": "m3", "model": {"builtin": {"type": "quarter-torus"}}, "grid": [2, 1, 1],
                                 "output": {"directory": str(tmp_path / "out"), "tolerance": 0.3, "format": "3mf"}})
    report = volpuzzle.build(spec, jobs=1)
    for p in report["pieces"]:
        objects = read_3mf(tmp_path / "out" / p["file"], strict=True)
        assert len(objects) == 1 and objects[0][3] is not None
    assert len(read_3mf(tmp_path / "out" / "puzzle.3mf", strict=True)) == len(report["pieces"])


def test_overflowing_parts_fill_few_plates_inside_and_apart():
    # 300 footprints over many plates: every one placed once, inside its plate, `spacing` from the others, on no
    # more plates than trimesh's own packer needs in one pass
    from trimesh.path import packing

    from volpuzzle.layout import _pack

    rng = np.random.default_rng(8)
    extents = rng.uniform(8, 70, (300, 2))
    plate, spacing = np.array([200.0, 150.0]), 3.0

    def plates_with(pack):
        remaining, placed = list(range(len(extents))), []
        while remaining:
            bounds, inserted = pack(extents[remaining], plate, spacing)
            assert inserted.any()
            chosen = [remaining[i] for i in np.flatnonzero(inserted)]
            placed.append((chosen, bounds))
            remaining = [r for j, r in enumerate(remaining) if not inserted[j]]
        return placed

    placed = plates_with(_pack)
    assert sorted(i for chosen, _ in placed for i in chosen) == list(range(len(extents)))
    for chosen, bounds in placed:
        assert np.all(bounds[:, 0] >= spacing / 2 - 1e-9) and np.all(bounds[:, 1] <= plate - spacing / 2 + 1e-9)
        size = np.ptp(bounds, axis=1)
        assert np.allclose(np.sort(size, axis=1), np.sort(extents[chosen], axis=1))  # turned at most 90 degrees
        lo, hi = bounds[:, 0], bounds[:, 1]
        gap = np.maximum(lo[None] - hi[:, None], lo[:, None] - hi[None]).max(axis=2)
        np.fill_diagonal(gap, np.inf)
        assert gap.min() >= spacing - 1e-9
    trimesh_once = plates_with(lambda e, p, s: packing.rectangles(e, size=p, spacing=s / 2, rotate=True, iterations=1))
    assert len(placed) <= len(trimesh_once)


@settings(max_examples=200, deadline=None)
@given(rects=st.lists(st.tuples(st.floats(0.0, 100.0), st.floats(0.0, 100.0)), min_size=0, max_size=12),
       part=st.tuples(st.floats(0.0, 110.0), st.floats(0.0, 110.0)))
def test_a_part_fits_the_packers_frontier_exactly_when_it_fits_a_free_rectangle(rects, part):
    # the packer skips a part that fits none of its frontier (_frontier) without measuring it: that must be exactly
    # the parts that fit no free rectangle either way round. Sides from a coarse grid, so that ties occur
    from volpuzzle.layout import _frontier

    rects = [(round(w / 5) * 5.0, round(h / 5) * 5.0) for w, h in rects]
    a, b = round(part[0] / 5) * 5.0, round(part[1] / 5) * 5.0
    free = np.array([(0.0, 0.0, w, h) for w, h in rects]).reshape(-1, 4)
    fits = any((w >= a and h >= b) or (w >= b and h >= a) for w, h in rects)
    frontier = _frontier(free, len(rects))
    assert fits == any(r1 >= min(a, b) and r2 >= max(a, b) for r1, r2 in frontier)
    # and the frontier is a few of the rectangles themselves, none beaten on both sides by another
    assert all((r1, r2) in {(min(w, h), max(w, h)) for w, h in rects} for r1, r2 in frontier)
    assert not any(p != q and q[0] >= p[0] and q[1] >= p[1] for p in frontier for q in frontier)


def test_step_pictures_show_the_pieces_in_place_grey_and_the_block_added_in_its_colour(tmp_path):
    from volpuzzle.preview import save_pictures, step_pictures

    a = trimesh.creation.box([10, 10, 10])
    b = trimesh.creation.box([10, 10, 10]).apply_translation([10, 0, 0])
    colors = np.array([[220, 40, 40], [40, 40, 220]], np.uint8)
    steps = [{"kind": "place", "piece": "a", "pieces": ["a"], "direction": None},
             {"kind": "join", "piece": "b", "pieces": ["b"], "direction": [0.0, 0.0, -1.0]}]
    files = save_pictures(tmp_path, step_pictures([a, b], ["a", "b"], colors, steps))
    assert files == ["step-01.png", "step-02.png"]
    first, second = (np.asarray(Image.open(tmp_path / f).convert("RGB")).astype(int) for f in files)
    assert first.shape == (270, 360, 3)
    first, second = first[25:], second[25:]  # below the title, whose letters are grey at their edges

    def red(px):
        return ((px[..., 0] > px[..., 2] + 60) & (px[..., 0] > px[..., 1] + 60)).sum()

    def blue(px):
        return ((px[..., 2] > px[..., 0] + 60) & (px[..., 2] > px[..., 1] + 60)).sum()

    def grey(px):
        return ((np.ptp(px, axis=2) < 4) & (px[..., 0] > 60) & (px[..., 0] < 250)).sum()

    assert red(first) > 500 and blue(first) == 0 and grey(first) < 50  # the first piece alone, in its colour
    assert blue(second) > 500 and red(second) == 0 and grey(second) > 500  # then it is in place, grey
    # b slides down onto its place, so it is drawn back up: above a's grey (beside it when in place, and a shade
    # lower on the screen, since +x runs slightly down)
    rows = np.arange(second.shape[0])
    b_rows = rows[(second[..., 2] > second[..., 0] + 60).any(axis=1)]
    g = (np.ptp(second, axis=2) < 4) & (second[..., 0] > 60) & (second[..., 0] < 250)
    assert b_rows.mean() < rows[g.any(axis=1)].mean() - 20


def test_hull_points_are_trimeshs_hull_vertices():
    # layout packs (and cages are fitted) on the hull's extreme points taken straight from qhull; they must be the
    # very points (and order) of trimesh's convex_hull, or plates and cages would move
    from volpuzzle.geometry import hull_points_of

    rng = np.random.default_rng(7)
    meshes = [trimesh.creation.icosphere(subdivisions=3), trimesh.creation.box([10, 30, 50]),
              trimesh.creation.cylinder(radius=4.0, height=12.0, sections=48)]
    bumpy = trimesh.creation.icosphere(subdivisions=3)
    bumpy.vertices *= rng.uniform(0.8, 1.2, (len(bumpy.vertices), 1))  # some vertices fall inside the hull
    meshes.append(bumpy)
    for k, mesh in enumerate(meshes):
        mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        fast = hull_points_of(mesh)
        if k == len(meshes) - 1:
            assert len(fast) < len(mesh.vertices)  # the test reaches points that are not on the hull
        np.testing.assert_array_equal(fast, trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
                                      .convex_hull.vertices)


def test_step_pictures_move_a_finished_block_whole_and_leave_no_copy_of_it_in_place(tmp_path):
    """A sub-assembly (c and d) joined onto another (a and b) is drawn back in its colours once: not also in place,
    where its pieces were drawn in the steps that assembled it (the pictures reuse those steps' depth buffers)."""
    from volpuzzle.preview import save_pictures, step_pictures

    boxes = [trimesh.creation.box([10, 10, 10]).apply_translation([10 * i, 0, 0]) for i in range(4)]
    colors = np.array([[220, 40, 40], [40, 200, 40], [40, 40, 220], [200, 40, 200]], np.uint8)
    down = [0.0, 0.0, -1.0]
    steps = [{"kind": "place", "piece": "a", "pieces": ["a"], "direction": None},
             {"kind": "join", "piece": "b", "pieces": ["b"], "direction": down},
             {"kind": "place", "piece": "c", "pieces": ["c"], "direction": None},
             {"kind": "join", "piece": "d", "pieces": ["d"], "direction": down},
             {"kind": "join", "piece": None, "pieces": ["c", "d"], "direction": down}]
    files = save_pictures(tmp_path, step_pictures(boxes, ["a", "b", "c", "d"], colors, steps))
    pics = [np.asarray(Image.open(tmp_path / f).convert("RGB")).astype(int)[25:] for f in files]

    def blue(px):  # c's colour
        return ((px[..., 2] > px[..., 0] + 60) & (px[..., 2] > px[..., 1] + 60)).sum()

    def grey(px):
        return (np.ptp(px, axis=2) < 4) & (px[..., 0] > 60) & (px[..., 0] < 250)

    assert blue(pics[2]) > 300  # c placed alone, in its colour
    assert blue(pics[4]) < 1.3 * blue(pics[2])  # c drawn once when its block moves, not also where it was placed
    assert abs(grey(pics[4]).sum() - grey(pics[2]).sum()) < 0.1 * grey(pics[2]).sum()  # only a and b, as before c
    # one frame for every step, so that they line up: a and b in place show at the same pixels in steps 3 and 5,
    # wherever neither picture draws a block over them
    from scipy.ndimage import binary_dilation

    def drawn_over(px):  # a block, its outline or the arrow, and a margin
        return binary_dilation((np.ptp(px, axis=2) >= 60) | (px.max(axis=2) < 60), iterations=3)

    free = ~drawn_over(pics[2]) & ~drawn_over(pics[4])
    assert grey(pics[2]).sum() > 300 and np.array_equal(grey(pics[2]) & free, grey(pics[4]) & free)


def test_step_bases_start_a_moved_block_from_the_pieces_in_place_before_it_was_begun():
    from volpuzzle.preview import _step_bases

    assert _step_bases([[0], [1], [2], [3], [2, 3], [0, 1, 2, 3]]) == [-1, -1, -1, -1, 2, 0]
    assert _step_bases([[0], [1], [0, 2]]) == [-1, -1, -2]  # 1 was placed after 0 and stays: drawn again
    assert _step_bases([[0, 1], [2], [0, 1]]) == [-1, -1, -2]
    assert _step_bases([]) == []


def test_a_simplified_piece_looks_up_its_original_triangles_only_for_a_texture(monkeypatch):
    from volpuzzle import preview

    sphere = trimesh.creation.icosphere(subdivisions=4)  # 5120 triangles, simplified to about 500
    calls = []
    real = preview._nearest
    monkeypatch.setattr(preview, "_nearest", lambda m, f: calls.append(f) or real(m, f))
    v, f, rgb = preview._part(sphere, (200, 30, 30), 500)
    assert len(f) < len(sphere.faces) and rgb.shape == (3,) and not calls  # one colour: no look-up
    colours = np.zeros((len(sphere.faces), 3), np.uint8)
    colours[sphere.triangles_center[:, 2] > 0] = (255, 255, 255)  # white north, black south
    v, f, rgb = preview._part(sphere, colours, 500)
    assert calls == [500] and rgb.shape == (len(f), 3)
    north = v[f].mean(axis=1)[:, 2] > 0.1
    south = v[f].mean(axis=1)[:, 2] < -0.1
    assert (rgb[north] == 255).all() and (rgb[south] == 0).all()
    assert preview._nearest(sphere, 5120) is None  # drawn as it is: colours stay as given
