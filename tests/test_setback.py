"""The face clearance where the cut faces meet at an apex (issue 10): a sphere cage's centre."""

import numpy as np
import pytest
import trimesh

from volpuzzle import geometry
from volpuzzle.compose.sampling import sample_parameters
from volpuzzle.compose.surface import cell_surface
from volpuzzle.pipeline import prepare
from volpuzzle.spec import load_spec

CLEARANCE = 0.15


@pytest.fixture(scope="module")
def wide_wedges(tmp_path_factory):
    """A ball in a sphere cage whose azimuth cells are 216 and 72 degrees wide: the polar cones meet at the centre,
    inside the model, and bend round it over more than half a turn in the wide cells."""
    tmp = tmp_path_factory.mktemp("apex")
    trimesh.creation.icosphere(1, radius=30.0).export(tmp / "ball.stl")
    (tmp / "s.yaml").write_text("name: apex\nmodel:\n  mesh: ball.stl\n  cage: {type: sphere, padding: 2}\n"
                                "grid: [1, 3, 3]\nsplits: {v: [0.38, 0.6], w: [0.6, 0.8]}\nperiodic: [w]\n"
                                "output: {tolerance: 0.2}\n")
    stages = prepare(load_spec(tmp / "s.yaml"))
    sampling = sample_parameters(stages.tiling, stages.fmap, 0.2)
    cells = {}
    for index, cell in stages.tiling.cells.items():
        v, f = cell_surface(cell, sampling, stages.fmap, face_clearance=CLEARANCE)
        cells[index] = geometry.manifold_from_mesh(v, f, str(index))
    return cells


@pytest.mark.parametrize("pair", [((0, 0, 0), (0, 1, 0)), ((0, 1, 0), (0, 2, 0)), ((0, 0, 1), (0, 1, 1)),
                                  ((0, 1, 1), (0, 2, 1))])
def test_cells_meeting_at_the_apex_keep_the_face_clearance(wide_wedges, pair):
    a, b = wide_wedges[pair[0]], wide_wedges[pair[1]]
    assert geometry.is_ok(a) and geometry.is_ok(b)
    # each side set back by half: the faces of the two cells, the centre included, a clearance apart
    assert a.min_gap(b, 3 * CLEARANCE) >= 0.75 * CLEARANCE


def test_the_apex_cells_still_fill_the_ball(wide_wedges):
    # the clearance takes a layer off each cut face, not a lump round the centre
    total = sum(float(m.volume()) for m in wide_wedges.values())
    assert total == pytest.approx(4 / 3 * np.pi * 32.0**3, rel=0.03)
