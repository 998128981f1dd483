"""Print readiness (issue 10): the face clearance between mating cut faces, the bed contact of every piece in its
print orientation, the bed margin, labels on every piece, and the preview's depth buffer."""

import numpy as np
import pytest
import trimesh
from test_compose import CASES, _orientation, _warp  # noqa: E402  (the small analytic models)

from volpuzzle import compose as C
from volpuzzle import geometry as G
from volpuzzle.check import closed_problem
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
        assert closed_problem(p.mesh) is None, p.id
    for f in t.faces:
        ma, mb = by_cell[f.lower].mesh, by_cell[f.upper].mesh
        a, b = G.from_trimesh(ma, "a"), G.from_trimesh(mb, "b")
        # everywhere, also where a cut face meets a collapsed axis or the outside
        assert a.min_gap(b, 5 * clearance) >= 0.9 * clearance, (f.lower, f.upper)
        # the two sides share one triangulation, each vertex moved by half the clearance along the same normals
        _, dist, _ = trimesh.proximity.closest_point(mb, ma.vertices)
        facing = dist[dist < 2 * clearance]
        assert len(facing) > 10
        assert facing.min() >= 0.9 * clearance and np.median(facing) == pytest.approx(clearance, rel=0.02)
    removed = sum(p.volume for p in plain) - sum(p.volume for p in gapped)
    assert removed == pytest.approx(C.face_clearance_volume(sampling, clearance), rel=0.03)


def _sheared_slab():
    """A block 40 x 6 x 12 mm sheared by 40 mm along x over its 6 mm in y: its cut face across u meets the outside
    (y = 0 and y = 6) at 8.5 degrees, acute on one side of the cut and obtuse on the other."""
    from test_compose import _clamped

    from volpuzzle.spline import Volume

    cp = np.zeros((2, 2, 2, 3))
    for i, j, k in np.ndindex(2, 2, 2):
        cp[i, j, k] = (40 * i + 40 * j, 6 * j, 12 * k)
    return Volume((1, 1, 1), (_clamped(2, 1),) * 3, cp)


@pytest.mark.parametrize("seed", [None, 5, 11])
def test_a_cut_meeting_the_outside_at_a_shallow_angle_keeps_the_whole_clearance(seed):
    # the corner must slide h / sin(8.5 deg) = 6.8 half-clearances along the outside (or move back along the cut):
    # sliding at most 4 left the neighbours 0.17 of 0.3 mm apart there; randomized, the angle varies along the edge
    clearance = 0.3
    vol = _sheared_slab()
    t = tile(vol, (2, 1, 2))
    fmap = Map(vol, None if seed is None else _warp(seed=seed), _orientation(vol))
    sampling = C.sample_parameters(t, fmap, 0.1)
    plain = C.compose(t, fmap, [], 0.1, sampling=sampling)
    gapped = C.compose(t, fmap, [], 0.1, sampling=sampling, face_clearance=clearance)
    by_cell = {p.cell: p for p in gapped}
    for p, q in zip(plain, gapped, strict=True):
        assert closed_problem(q.mesh) is None, q.id
        assert q.volume < p.volume
    for f in t.faces:
        a, b = G.from_trimesh(by_cell[f.lower].mesh, "a"), G.from_trimesh(by_cell[f.upper].mesh, "b")
        assert a.min_gap(b, 5 * clearance) >= 0.95 * clearance, (f.lower, f.upper)
    removed = sum(p.volume for p in plain) - sum(p.volume for p in gapped)
    assert removed == pytest.approx(C.face_clearance_volume(sampling, clearance), rel=0.03)


def test_check_warns_where_neighbours_come_closer_than_the_clearance_less_the_tessellation(monkeypatch):
    from volpuzzle import check

    report = {"spec": {"output": {"face_clearance": 0.15, "labels": False}}, "pieces": [],
              "checks": {"face_clearance_mm": 0.15, "tessellation_tolerance_mm": 0.02},
              "joints": [{"clearance_mm": 0.15, "radius_mm": 2.5, "length_mm": 6}]}
    meshes = {"p0-0-0": trimesh.creation.box([1, 1, 1]), "p1-0-0": trimesh.creation.box([1, 1, 1])}
    assert check.least_face_gap(0.15, report["joints"], 0.02) == pytest.approx(0.13)
    assert check.least_face_gap(0.15, [{"clearance_mm": 0.1}], 0.1) == pytest.approx(0.075)  # a pin's fit is less
    for smallest, warned in ((0.125, True), (0.135, False)):
        monkeypatch.setattr(check, "_face_gaps", lambda *_a, s=smallest: [("p0-0-0", "p1-0-0", 0.15, s)])
        got = check.check_printability(report, meshes)
        expected = ("pieces p0-0-0 and p1-0-0 come within 0.125 mm of each other at one spot (expected at least "
                    "0.130 mm: the face clearance 0.15 mm less the tessellation's)")
        assert (expected in got["warnings"]) == warned, got["warnings"]
        assert got["min_face_gap_mm"] == smallest


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


@pytest.mark.slow
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


@pytest.mark.slow
def test_preview_takes_a_colour_per_triangle_and_draws_a_plate(tmp_path):
    from PIL import Image

    from volpuzzle.preview import render_preview

    box = trimesh.creation.box([20, 20, 20])
    per_tri = np.tile(np.array([[30, 200, 30]], np.uint8), (len(box.faces), 1))
    per_tri[box.face_normals[:, 2] > 0.5] = (200, 30, 200)  # the top painted another colour
    render_preview(tmp_path / "p.png", [box], [per_tri], plate=([(0, np.eye(4))], (60, 50)))
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


def test_check_from_files_finds_faces_that_close():
    from volpuzzle.check import check_printability

    report = {"spec": {"output": {"face_clearance": 0.3, "labels": False}}, "pieces": [], "joints": []}
    _, _, plain = _pieces("warped", 0.0)
    _, _, gapped = _pieces("warped", 0.3)
    closed = check_printability(report, {p.id: p.mesh for p in plain})
    assert any("face each other 0.000 mm apart" in f for f in closed["failures"])
    ok = check_printability(report, {p.id: p.mesh for p in gapped})
    assert ok["failures"] == [] and ok["median_face_gap_mm"] == pytest.approx(0.3, rel=0.02)


# ---------------------------------------------------------------------------------------------------------------------
# bed contact, pins up, margin


def test_a_piece_without_a_flat_face_gets_a_base_cut_that_holds_it():
    from volpuzzle.layout import MIN_BED_MM2, base_cut, bed_contact, plan_pose

    ball = trimesh.creation.icosphere(subdivisions=4, radius=15.0)
    assert bed_contact(ball.vertices, ball.faces) < MIN_BED_MM2  # on a point, as it is
    pose = plan_pose(ball)
    assert 0 < pose.base_cut_mm <= 0.6
    cut, removed = base_cut(ball, pose)
    assert closed_problem(cut) is None, "cut ball"
    assert removed == pytest.approx(ball.volume - cut.volume, rel=1e-6) and 0 < removed < 0.01 * ball.volume
    placed = cut.copy().apply_transform(pose.rotation)
    assert bed_contact(placed.vertices, placed.faces) >= 25.0 - 1e-6  # BASE_TARGET[0]
    # the cut is on the side that goes down
    lowest = placed.vertices[:, 2].min()
    flat = placed.face_normals[:, 2] < -0.999
    assert np.all(placed.triangles_center[flat][:, 2] < lowest + 1e-6)


def test_bed_contact_of_a_piece_placed_by_a_transform_is_that_of_the_placed_mesh():
    from volpuzzle.check import piece_bed_contact
    from volpuzzle.layout import bed_contact

    box = trimesh.creation.box([20, 12, 6])
    tilt = trimesh.transformations.rotation_matrix(0.02, [1, 0.3, 0])  # resting on one edge of its 20 x 12 face
    tilt[:3, 3] = [40, 30, 7]
    placed = box.copy().apply_transform(tilt)
    want = bed_contact(placed.vertices, placed.faces)
    assert 0 < want < 20 * 12 - 1  # a strip along the low edge, not the whole face
    got = piece_bed_contact(box, tilt)
    assert got == pytest.approx(want, rel=1e-9)
    assert piece_bed_contact(box, tilt) == got
    flat = np.eye(4)
    assert piece_bed_contact(box, flat) == pytest.approx(20 * 12, rel=1e-9)  # another placement, measured


def test_a_small_round_piece_gets_a_deeper_cut_rather_than_too_little_bed():
    from volpuzzle.layout import BASE_CUT_MM, MIN_BED_MM2, base_cut, bed_contact, plan_pose

    # a 2 mm ball: 0.6 mm (the deepest shallow cut) leaves it on about 8 mm^2, under what a first layer holds
    ball = trimesh.creation.icosphere(subdivisions=4, radius=2.0)
    pose = plan_pose(ball)
    assert pose.base_cut_mm > BASE_CUT_MM[-1] and pose.bed_contact_mm2 >= MIN_BED_MM2
    cut, _ = base_cut(ball, pose)
    placed = cut.copy().apply_transform(pose.rotation)
    assert bed_contact(placed.vertices, placed.faces) >= MIN_BED_MM2


def _small_shell_build_is_refused(tmp_path, pattern):
    """A 2x2x1 sphere shell build fails with GeometryError matching pattern, and writes no folder."""
    from helpers_build import example_spec

    import volpuzzle
    from volpuzzle.errors import GeometryError

    spec = example_spec("sphere-shell", tmp_path, tolerance=1.0, grid=[2, 2, 1], randomize=None)
    with pytest.raises(GeometryError, match=pattern):
        volpuzzle.build(spec, jobs=1)
    assert not (tmp_path / "out" / "sphere-shell").exists()


def test_a_build_whose_piece_would_rest_on_too_little_bed_is_refused(tmp_path, monkeypatch):
    from volpuzzle import layout

    # as if every piece, laid out, touched the bed on 5 mm^2: `check` would refuse the folder, so the build must
    monkeypatch.setattr(layout, "bed_contact", lambda *_args, **_kwargs: 5.0)
    _small_shell_build_is_refused(tmp_path, r"sphere-shell: pieces p0-0-0, .* rest on less than 10 mm\^2 of the bed "
                                            r"even with a base cut of [0-9.]+ mm \(expected at least 10 mm\^2 each")


def test_a_flat_face_needs_no_cut_and_pins_go_up():
    from volpuzzle.layout import PIN_UP_DEG, plan_pose

    cube = trimesh.creation.box([20, 20, 20])
    pin = np.array([1.0, 0.0, 0.0])
    pose = plan_pose(cube, [pin])
    assert pose.base_cut_mm == 0 and pose.bed_contact_mm2 == pytest.approx(400.0, rel=1e-3)
    assert pose.pins_up == 1 and (pose.rotation[:3, :3] @ pin)[2] >= np.cos(np.radians(PIN_UP_DEG))
    # a hole must not open onto the bed: with its opening along -z the cube is not laid on its top
    pose = plan_pose(cube, [], [np.array([0.0, 0.0, 1.0])])
    assert pose.holes_down == 0 and (pose.rotation[:3, :3] @ np.array([0.0, 0.0, 1.0]))[2] > -0.5


def test_layout_keeps_the_margin_and_centres_the_plate():
    from volpuzzle.layout import layout

    rng = np.random.default_rng(5)
    parts = [(f"p{i}", trimesh.creation.box(rng.uniform(10, 30, 3))) for i in range(6)]
    plate, margin = np.array([250.0, 210.0]), 10.0
    placements, plates = layout(parts, plate, 4.0, margin=margin)
    meshes = dict(parts)
    for pl in plates:
        boxes = np.array([meshes[p.name].copy().apply_transform(p.transform).bounds for p in placements
                          if p.plate == pl.index])
        lo, hi = boxes[:, 0, :2].min(axis=0), boxes[:, 1, :2].max(axis=0)
        assert np.all(lo >= margin - 1e-6) and np.all(hi <= plate - margin + 1e-6)
        assert (lo + hi) / 2 == pytest.approx(plate / 2, abs=1e-6)


def test_margin_that_leaves_no_room_is_refused(tmp_path):
    from helpers_build import write_spec

    from volpuzzle.errors import SpecError
    from volpuzzle.spec import load_spec

    spec = write_spec(tmp_path, {"name": "m", "model": {"builtin": {"type": "quarter-torus"}}, "grid": [1, 1, 1],
                                 "output": {"plate": [100, 60], "margin": 30}})
    with pytest.raises(SpecError, match=r"output.margin: leaves no room on the plate \(got 30, expected less than "):
        load_spec(spec)
    spec = write_spec(tmp_path, {"name": "m", "model": {"builtin": {"type": "quarter-torus"}}, "grid": [1, 1, 1],
                                 "output": {"face_clearance": 2}})
    with pytest.raises(SpecError, match=r"output.face_clearance: would leave the pieces loose \(got 2, expected"):
        load_spec(spec)


# ---------------------------------------------------------------------------------------------------------------------
# a small build: every piece labelled, on the bed, and the files say so


@pytest.mark.slow
def test_small_build_every_piece_labelled_on_its_bed_and_checked_from_files(tmp_path):
    import json

    from helpers_build import write_spec

    import volpuzzle
    from volpuzzle.check import check_directory

    spec = write_spec(tmp_path, {"name": "small", "model": {"builtin": {"type": "quarter-torus"}}, "grid": [2, 1, 2],
                                 "randomize": {"seed": 1, "amplitude": 0.2, "control_points": 5},
                                 "output": {"directory": str(tmp_path / "out"), "tolerance": 0.3}})
    report = volpuzzle.build(spec, jobs=1)
    out = tmp_path / "out"
    written = json.loads((out / "report.json").read_text(encoding="utf-8"))
    joints = written["joints"]
    for p in written["pieces"]:
        assert p["label"]["text"], p["id"]
        assert p["print"]["bed_contact_mm2"] >= 10.0
        if not p["label"]["on_joint_face"]:
            # no joint of the piece opens on the label's face
            n, c = np.array(p["label"]["normal"]), np.array(p["label"]["center_mm"])
            for j in joints:
                if p["id"] in (j["pin_piece"], j["hole_piece"]):
                    facing = abs(np.dot(j["direction"], n)) > 0.7
                    assert not (facing and abs(np.dot(np.array(j["center_mm"]) - c, n)) < 2)
    assert report["checks"]["face_clearance_mm"] == 0.15 and report["checks"]["face_clearance_mm3"] > 0
    printable = check_directory(out)["printability"]
    assert printable["unlabelled"] == [] and printable["pieces_under_bed_minimum"] == []
    assert printable["median_face_gap_mm"] == pytest.approx(0.15, rel=0.05)
    md = (out / "report.md").read_text(encoding="utf-8")
    assert "Every piece carries a label" in md and "## Fit" in md and "face clearance 0.15 mm" in md
    html = (out / "instructions.html").read_text(encoding="utf-8")
    steps = written["assembly"]["pictures"]
    assert steps and all((out / s).is_file() for s in steps) and html.count("<li>") == len(steps)
    plate = written["plates"][0]
    from volpuzzle.io.threemf import read_3mf

    xy = np.concatenate([v[:, :2] for _, v, _, _ in read_3mf(out / plate["file"])])
    assert xy.min() >= 10.0 - 1e-3 and np.all(xy.max(axis=0) <= np.array([250.0, 210.0]) - 10.0 + 1e-3)


def test_pins_below_the_printable_minimum_are_warned_of():
    from volpuzzle.check import fit_line, pin_fit

    fit = pin_fit("pin", 0.8, 2.0, 0.15, 0.3, 0.15)
    assert fit["pin_diameter_mm"] == 1.6
    assert fit["warnings"] == [
        "joints.radius: pins of radius 0.8 mm are below the printable minimum (expected at least 1 mm)",
        "joints.length: pins 2 mm long are below the printable minimum (expected at least 3 mm)"]
    assert pin_fit("pin", 2.5, 6, 0.15, 0.3, 0.15)["warnings"] == []
    assert "5 mm across, 6 mm long, clearance 0.15 mm radial" in fit_line(pin_fit("pin", 2.5, 6, 0.15, 0.3, 0.15))


def test_pins_smaller_than_asked_are_said_in_the_fit():
    from types import SimpleNamespace as NS

    from volpuzzle.check import fit_line
    from volpuzzle.report import fit

    def joint(r, length):
        return NS(radius=r, length=length, clearance=0.15, axial_clearance=0.3)

    def spec(radius, length):
        return NS(joints=NS(style="pin", radius=radius, length=length, clearance=0.15, axial_clearance=0.3))

    joints = [joint(3.5, 11.65), joint(30.0, 100.0)]
    got = fit(spec(30.0, 100.0), joints, 0.15)
    assert got["shrunk"] == {"joints": 1, "of": 2, "asked_radius_mm": 30.0, "asked_length_mm": 100.0}
    assert fit_line(got).endswith("; 1 of 2 shrunk to fit their faces (joints asked radius 30 mm and length 100 mm)")
    # sizes the joint stage chose itself (none asked) are not 'shrunk'; neither are pins of the asked size
    assert "shrunk" not in fit(spec(None, None), joints, 0.15)
    assert "shrunk" not in fit_line(fit(spec(3.5, None), [joint(3.5, 11.65)], 0.15))


def test_check_from_files_names_a_piece_on_a_point_and_a_thin_pin():
    from volpuzzle.check import check_printability

    cone = trimesh.creation.cone(radius=10, height=20)
    flip = trimesh.transformations.rotation_matrix(np.pi, [1, 0, 0])  # tip down
    report = {"spec": {"output": {"face_clearance": 0.0}},
              "pieces": [{"id": "p0", "print": {"plate_transform": flip.tolist()}, "label": {"text": "p0"}}],
              "joints": [{"pin_piece": "p0", "hole_piece": "p1", "radius_mm": 0.5, "length_mm": 6, "style": "pin"}]}
    result = check_printability(report, {"p0": cone})
    assert result["pieces_under_bed_minimum"] == ["p0"]
    assert "pieces p0 rest on less than 10 mm^2 of the bed" in result["failures"]
    assert result["warnings"] == ["1 of 1 joints (first p0 -> p1) have pins below the printable minimum (radius down "
                                  "to 0.5 mm, length down to 6 mm; expected at least 1 and 3 mm)"]
    upright = check_printability(dict(report, joints=[]), {"p0": cone.copy().apply_transform(flip)})
    # the same transform applied to a cone already tip down puts it on its base
    assert upright["failures"] == [] and upright["min_bed_contact_mm2"] > 300


def test_check_from_files_names_a_piece_whose_bed_contact_cannot_be_measured():
    # a placement that is not a number (a hand-edited report), a file without triangles or one with a hole (whose
    # section would be a number without meaning): said, never passed
    from volpuzzle.check import check_printability

    box = trimesh.creation.box([10, 10, 10])
    broken = np.eye(4)
    broken[0, 3] = np.nan
    holed = trimesh.Trimesh(box.vertices, box.faces[1:], process=False)
    report = {"spec": {"output": {"face_clearance": 0.0}},
              "pieces": [{"id": f"p{k}", "print": {"plate_transform": (broken if k == 0 else np.eye(4)).tolist()},
                          "label": {"text": f"p{k}"}} for k in range(3)]}
    result = check_printability(report, {"p0": box, "p1": trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int)),
                                         "p2": holed})
    assert result["failures"] == [
        "piece p0: bed contact not measured (piece on the bed: the mesh has non-finite vertex coordinates)",
        "piece p1: bed contact not measured (piece on the bed: the mesh encloses no volume (empty solid from 0 "
        "triangles))",
        "piece p2: bed contact not measured (piece on the bed: the mesh is not a closed solid: not watertight (3 open "
        "edges))"]
    assert result["bed_contact_mm2"] == {}


def test_a_mirroring_placement_rests_on_the_same_area_as_its_mirror_image():
    # a hand-edited report may mirror a piece (determinant -1): its triangles then face inwards, and the section's
    # sign must not turn a good contact into a negative one
    from volpuzzle.check import check_printability, piece_bed_contact

    box = trimesh.creation.box([10, 12, 10])
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    mirror[2, 3] = 5.0
    assert piece_bed_contact(box, mirror) == pytest.approx(120.0, rel=1e-12)
    report = {"spec": {"output": {"face_clearance": 0.0}},
              "pieces": [{"id": "p0", "print": {"plate_transform": mirror.tolist()}, "label": {"text": "p0"}}]}
    result = check_printability(report, {"p0": box})
    assert result["bed_contact_mm2"] == {"p0": 120.0} and not result["failures"]


def test_a_label_with_no_inner_face_goes_mirrored_on_the_bed_side():
    from volpuzzle.geometry import from_trimesh
    from volpuzzle.label import DEPTH_MM, engrave_bed

    slab = trimesh.creation.box([30, 20, 8])
    turn = trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])  # printed on its 30 x 8 side
    body = from_trimesh(slab, "slab")
    out, site = engrave_bed(body, turn, "p1-0-0")
    assert site["face"] == "bed" and site["mirrored"] and site["height_mm"] >= 2.5
    removed = body.volume() - out.volume()
    assert removed > 0
    # every bit taken lies within the groove's depth of the bed side: turned back, the y = -10 face
    groove = body - out
    lo, hi = np.asarray(groove.bounding_box()).reshape(2, 3)
    assert lo[1] >= -10 - 1e-6 and hi[1] <= -10 + DEPTH_MM + 1e-6
    assert np.allclose(site["normal"], [0, -1, 0], atol=1e-9)
    tiny = trimesh.creation.box([3, 3, 3])
    assert engrave_bed(from_trimesh(tiny, "tiny"), np.eye(4), "p0-0-0")[1] is None


def test_a_base_cut_drops_a_speck_it_parts_from_the_piece_but_refuses_to_cut_a_piece_in_two():
    from volpuzzle.errors import GeometryError
    from volpuzzle.layout import Pose, base_cut

    def piece(bump):
        # a 10 mm block and a bump tied to it only by a 0.1 mm film on the bed, which the 0.2 mm flat cuts away
        parts = [trimesh.creation.box(bounds=[[0, 0, 0], [10, 10, 10]]),
                 trimesh.creation.box(bounds=[[9, 0, 0], [20 + bump, 0.5, 0.1]]),
                 trimesh.creation.box(bounds=[[20, 0, 0], [20 + bump, 0.5, bump]])]
        body = G.from_trimesh(parts[0], "block")
        for p in parts[1:]:
            body = body + G.from_trimesh(p, "part")
        return G.to_trimesh(body)

    pose = Pose(np.eye(4), np.array([0.0, 0.0, -1.0]), 0.2, 100.0, 0, 0, 0, 0)
    cut, removed = base_cut(piece(0.5), pose)  # the bump above the cut: 0.5 x 0.5 x 0.3 = 0.075 mm^3
    assert closed_problem(cut) is None, "cut"
    assert cut.volume == pytest.approx(1000 - 0.2 * 100, rel=1e-9) and removed > 20
    with pytest.raises(GeometryError, match=r"\(base cut\): the mesh has 2 separate bodies"):
        base_cut(piece(3.0), pose)  # 3 x 0.5 x 2.8 mm is a part of the piece, not a speck
    thin = trimesh.creation.box(bounds=[[0, 0, 0], [10, 10, 0.1]])
    with pytest.raises(GeometryError, match=r"plate \(base cut\): the mesh has no triangles"):
        base_cut(thin, pose, "plate")  # a 0.2 mm flat leaves nothing of a 0.1 mm plate


def test_a_build_whose_facing_cut_faces_close_is_refused_before_it_is_written(tmp_path, monkeypatch):
    from volpuzzle import check

    # as if two neighbours' cut faces met (median gap 0 where the face clearance asks 0.15 mm): check would refuse
    monkeypatch.setattr(check, "_face_gaps", lambda meshes, *_args: [(sorted(meshes)[0], sorted(meshes)[1], 0.0, 0.0)])
    _small_shell_build_is_refused(tmp_path, r"sphere-shell: not printable as laid out: pieces p0-0-0 and p0-1-0 face "
                                            r"each other 0.000 mm apart .*expected the face clearance 0.15 mm")


# ---------------------------------------------------------------------------------------------------------------------
# loose dowels printed flat


def test_loose_dowels_lie_flat_on_the_plate_on_a_flat_that_holds_them():
    import manifold3d as m3

    from volpuzzle.layout import MIN_BED_MM2, bed_contact, lay_dowels_flat, layout

    class Joint:  # the one field lay_dowels_flat reads of a joint
        def __init__(self, direction):
            self.direction = np.asarray(direction, float)

    dirs = [(0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.6, 0.0, 0.8)]
    dowels = []
    for k, d in enumerate(dirs):
        rod = m3.Manifold.cylinder(12.0, 2.5, 2.5, 24).translate((0.0, 0.0, -6.0))
        frame = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], d)
        frame[:3, 3] = (30.0 * k, 5.0, 7.0)
        dowels.append((f"dowel-{k:02d}", G.to_trimesh(rod.transform(frame[:3, :]))))
    flat, poses = lay_dowels_flat(dowels, [Joint(d) for d in dirs])
    places, _ = layout(flat, (250, 210), 4.0, poses=poses, margin=10.0)
    for (name, mesh), (_, before), d, place in zip(flat, dowels, dirs, places, strict=True):
        axis = place.transform[:3, :3] @ np.asarray(d)
        assert abs(axis[2]) < 1e-6, name  # the dowel's axis lies in the plate
        assert 0 < poses[name].base_cut_mm <= 0.6  # a shallow flat along its side, not a deep one
        assert bed_contact(mesh.vertices, mesh.faces, place.transform) >= MIN_BED_MM2
        lost = before.volume - mesh.volume
        assert 0 < lost < 0.05 * before.volume  # the dowel keeps its size: only the flat is taken off
        assert closed_problem(mesh) is None, name


# ---------------------------------------------------------------------------------------------------------------------
# every piece labelled: a small mesh model (whose cut faces lie partly off the pieces) and a small shell (whose cut
# faces are as thin as the wall)


@pytest.mark.slow
def test_small_mesh_build_labels_every_piece_and_keeps_the_face_clearance(tmp_path, monkeypatch):
    from helpers_build import example_spec

    import volpuzzle
    from volpuzzle import label

    asked = []
    labelled = label.label_pieces

    def spy(*args, **kwargs):
        asked.append(kwargs.get("cut_by_mesh"))
        return labelled(*args, **kwargs)

    monkeypatch.setattr(label, "label_pieces", spy)
    report = volpuzzle.build(example_spec("gear-cylinder", tmp_path, tolerance=0.2), jobs=1)
    labels = {p["id"]: p["label"] for p in report["pieces"]}
    assert all(v.get("text") for v in labels.values()), labels
    assert asked == [True]  # sought on the pieces' own faces, not the cage cells'
    printable = report["checks"]["printability"]
    assert printable["unlabelled"] == [] and not printable["failures"]
    # neighbours apart by the clearance, and the volume it took is in the volume check
    assert report["checks"]["face_clearance_mm"] == 0.15 and report["checks"]["face_clearance_mm3"] > 0
    assert printable["median_face_gap_mm"] == pytest.approx(0.15, rel=0.05)
    assert abs(report["checks"]["volume_error"]) < 0.005


@pytest.mark.slow
def test_small_shell_build_labels_every_piece(tmp_path):
    from helpers_build import example_spec

    import volpuzzle

    report = volpuzzle.build(example_spec("sphere-shell", tmp_path, tolerance=0.4, grid=[3, 4, 1]), jobs=1)
    labels = {p["id"]: p["label"] for p in report["pieces"]}
    assert all(v.get("text") for v in labels.values()), labels
    assert report["checks"]["printability"]["unlabelled"] == []
    # the wall is too thin for text on its cut faces of the poles' pieces: the hidden inside of the shell holds them
    assert any(v.get("on_outer_face") for v in labels.values())
