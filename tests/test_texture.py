"""texture: image colours on the outer face, carried in 3MF colour groups (issue 11)."""

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from volpuzzle.io.threemf import read_3mf, read_triangle_colors, write_3mf
from volpuzzle.models import sphere_shell
from volpuzzle.spec import TextureSpec
from volpuzzle.texture import blend, texture_pieces

IMAGE = Path(__file__).parent / "data" / "images" / "earth_256x128.png"


class _Piece:
    def __init__(self, pid, mesh):
        self.id, self.mesh = pid, mesh


def _direction(lat, lon):
    """Outward unit vector of the sphere shell's outside at a latitude and longitude, degrees. The map's left edge
    (longitude -180) sits at azimuth 0 (v = 0), and v runs eastward, so azimuth = longitude + 180."""
    th, ph = math.radians(90 - lat), math.radians(lon + 180)
    return np.array([math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)])


def _patch(r, lat, lon, size=8.0):
    """A closed piece of the outside: the sphere triangles within `size` degrees of a place, plus a box inside."""
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=r)
    keep = np.degrees(np.arccos(np.clip(sphere.triangles_center @ _direction(lat, lon) / r * 1.0001, -1, 1))) < size
    return sphere.submesh([np.flatnonzero(keep)], append=True)


def test_sahara_is_sand_and_the_pacific_blue_in_a_strict_3mf(tmp_path):
    vol = sphere_shell(outer_radius=50.0, inner_radius=40.0)
    pieces = [_Piece("sahara", _patch(50.0, 23, 12)), _Piece("pacific", _patch(50.0, -5, -140)),
              _Piece("inside", _patch(40.0, 23, 12))]
    colors, report = texture_pieces(TextureSpec(image=IMAGE), vol, pieces, tolerance=0.2)
    assert report["textured_triangles"] > 0
    assert np.all(colors["inside"] == -1)  # the inner face keeps the piece colour
    own = {"sahara": (200, 30, 30), "pacific": (30, 200, 30), "inside": (30, 30, 200)}
    objs = [(p.id, p.mesh.vertices, p.mesh.faces, own[p.id], None) for p in pieces]
    path = write_3mf(tmp_path / "t.3mf", objs, colors=[colors[p.id] for p in pieces])
    assert len(read_3mf(path, strict=True)) == 3  # strict mode: no warnings
    got = read_triangle_colors(path, strict=True)
    sand = got["sahara"].astype(float).reshape(-1, 3).mean(axis=0)
    sea = got["pacific"].astype(float).reshape(-1, 3).mean(axis=0)
    assert sand[0] > sand[2] + 30 and sand[1] > sand[2]  # yellow-brown
    assert sea[2] > sea[0] + 20  # blue
    assert np.all(got["inside"] == own["inside"])
    for p in pieces:
        assert np.array_equal(got[p.id], blend(own[p.id], colors[p.id]))


def test_texture_spec_key(tmp_path):
    from volpuzzle.errors import SpecError
    from volpuzzle.spec import load_spec_text

    (tmp_path / "e.png").write_bytes(IMAGE.read_bytes())
    spec = load_spec_text("name: e\nmodel: {builtin: sphere-shell}\ngrid: [2, 2, 1]\ntexture: {image: e.png}\n",
                          tmp_path / "s.yaml")
    assert spec.texture.face == "w_max" and spec.texture.image == tmp_path / "e.png"
    with pytest.raises(SpecError, match=r"texture.face: .*got 'outside'"):
        load_spec_text("name: e\nmodel: {builtin: sphere-shell}\ngrid: [2, 2, 1]\n"
                       "texture: {image: e.png, face: outside}\n", tmp_path / "s.yaml")
    (tmp_path / "m.stl").write_bytes(trimesh.creation.box().export(file_type="stl"))
    with pytest.raises(SpecError, match=r"texture: not for a mesh model \(got a texture with model.mesh"):
        load_spec_text("name: e\nmodel: {mesh: m.stl}\ngrid: [2, 2, 1]\ntexture: {image: e.png}\n",
                       tmp_path / "s.yaml")


@pytest.mark.slow
def test_stl_output_says_it_cannot_hold_colour(tmp_path, capsys):
    import dataclasses

    from volpuzzle.spec import load_spec_text
    from volpuzzle.texture import build_texture

    (tmp_path / "e.png").write_bytes(IMAGE.read_bytes())
    spec = load_spec_text("name: e\nmodel: {builtin: sphere-shell}\ngrid: [2, 2, 1]\ntexture: {image: e.png}\n"
                          "output: {format: stl}\n", tmp_path / "s.yaml")
    volume = sphere_shell(50.0, 40.0)
    pieces = [_Piece("sahara", _patch(50.0, 23, 12))]
    colors, report = build_texture(spec, volume, pieces, 0.2)
    assert "STL cannot hold colour" in report["note"]
    assert "warning: texture: STL cannot hold colour" in capsys.readouterr().err
    spec3 = dataclasses.replace(spec, output=dataclasses.replace(spec.output, format="3mf"))
    assert "note" not in build_texture(spec3, volume, pieces, 0.2)[1]
    assert colors["sahara"].shape == (len(pieces[0].mesh.faces), 3, 3)
