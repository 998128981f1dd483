"""The paper's duck (specs/duck.yaml): a 4.5 mm shell, 30% outside the surface, 32 pieces, pinned (issues 9, 11)."""

import pytest
from helpers_build import example_spec

import volpuzzle
from volpuzzle.check import check_directory
from volpuzzle.joint import report_figures


@pytest.mark.slow
def test_duck_holds_together(tmp_path):
    report = volpuzzle.build(example_spec("duck", tmp_path, tolerance=0.2), jobs=1)
    shell = report["model"]["shell"]
    assert shell["inward_mm"] + shell["outward_mm"] == pytest.approx(shell["thickness_mm"])
    assert shell["outward_mm"] > 0 and shell["inward_mm"] > 0
    # both walls within the fit's target of their true offsets
    assert shell["offset_max_error_mm"] <= shell["offset_target_mm"]
    assert max(shell["inner_offset_max_error_mm"], shell["outer_offset_max_error_mm"]) == shell["offset_max_error_mm"]
    fig = report_figures(report)
    assert fig["pieces"] == 32 and fig["pieces_without_joint"] == [] and fig["parts"] == 1
    # every face with room but no pin says why (on the duck: its split slides off the face's normal across the wall)
    unpinned = [c for c in report["contacts"] if c["room"] and not c["pinned"]]
    assert all(c["reason"] for c in unpinned) and fig["pinned_with_room"] + len(unpinned) == fig["with_room"]
    # issue 9's target: cut round the body before across it, the splits lean little enough (54 of 56 here)
    assert fig["with_room"] == 56 and fig["pinned_with_room"] >= 0.9 * fig["with_room"]
    assert report["checks"]["max_overlap_mm3"] == 0.0  # no pin reaches into a third piece
    assert all(j["radius_mm"] >= 1.0 for j in report["joints"])  # printable: joint.MIN_RADIUS
    assert not report["assembly"]["welded"] and not report["assembly"]["stuck"]
    checks = check_directory(tmp_path / "out" / "duck")
    assert checks["joint_graph"]["pieces_without_joint"] == []


@pytest.mark.slow
def test_the_cells_round_the_head_top_pole_keep_the_face_clearance():
    # Eight 45-degree cells meet at the top of the head. On the skin beside a cut, both cells' points lie a fraction
    # of a clearance from it; fading with their edge's slide they moved too little, and two neighbours came within
    # 0.088 of the 0.15 mm (issue 10). Each such point now moves away from the cut by what it lacks.
    from conftest import REPO

    from volpuzzle import compose as C
    from volpuzzle import geometry as G
    from volpuzzle.pipeline import prepare
    from volpuzzle.spec import load_spec

    spec = load_spec(REPO / "specs" / "duck.yaml")
    st = prepare(spec)
    clearance, tol = spec.output.face_clearance, spec.output.tolerance
    sampling = C.sample_parameters(st.tiling, st.fmap, tol)
    cells = [(0, 3, 0), (0, 4, 0), (0, 5, 0)]

    def solid(surfaces, cell):
        return G.manifold_from_mesh(*surfaces[cell], str(cell))

    plain = {c: C.cell_surface(st.tiling.cells[c], sampling, st.fmap) for c in cells}
    apart = {c: C.cell_surface(st.tiling.cells[c], sampling, st.fmap, clearance) for c in cells}
    for a, b in ((cells[0], cells[1]), (cells[1], cells[2])):
        # closed cells touch; set back, they keep the clearance less the tessellation's wobble on the skin's curve
        assert solid(plain, a).min_gap(solid(plain, b), 1.0) < 1e-6
        assert solid(apart, a).min_gap(solid(apart, b), 1.0) >= 0.95 * clearance, (a, b)
