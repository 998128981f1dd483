"""The tile stage's own refusal: a grid whose pieces are thinner than about ten tolerances names the grid and the
tolerance that would fit."""

import pytest

from volpuzzle.errors import SpecError
from volpuzzle.mapping import Map
from volpuzzle.models import make_builtin
from volpuzzle.spec import load_spec_text
from volpuzzle.tile import check_grid_vs_tolerance, tile


def _spec(grid, tolerance):
    return load_spec_text("name: thin\nmodel: {builtin: {type: quarter-torus, major_radius: 50, minor_radius: 20}}\n"
                          f"grid: {list(grid)}\njoints: {{style: none}}\noutput: {{tolerance: {tolerance}}}\n")


def _check(spec):
    vol = make_builtin({"type": "quarter-torus", "major_radius": 50, "minor_radius": 20})
    check_grid_vs_tolerance(spec, tile(vol, spec.grid), Map(vol))


def test_pieces_too_thin_for_the_tolerance_name_the_grid_that_fits():
    # the quarter torus is 72 mm long along w: 12 pieces are 6 mm, under ten tolerances of 1 mm
    with pytest.raises(SpecError, match=r"grid: 12 pieces along w make pieces 6\.03 mm thin, too thin for "
                                        r"output\.tolerance 1 mm \(got 12, expected at most 7 along w or "
                                        r"output\.tolerance at most 0\.603 mm\)"):
        _check(_spec((1, 1, 12), 1.0))


def test_pieces_too_thin_for_any_grid_ask_for_a_finer_tolerance():
    with pytest.raises(SpecError, match=r"grid: 1 pieces along u .*\(got 1, expected output\.tolerance at most "):
        _check(_spec((1, 1, 1), 5.0))


def test_pieces_ten_tolerances_thick_pass():
    _check(_spec((1, 1, 7), 1.0))
