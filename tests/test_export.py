"""The export stage and the 3MF writer: files, read-back, atomicity, determinism."""

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

import volpuzzle.export as export_mod
from volpuzzle.check import check_directory, check_pieces, closed_problem
from volpuzzle.errors import ExportError, GeometryError, ModelError
from volpuzzle.export import clean_json, piece_colors, report_piece_entry, write_build
from volpuzzle.io.threemf import read_3mf, write_3mf


def make_pieces(n=2, size=10.0):
    """Pieces as compose.Piece would hand them over: id, cell, closed mesh in mm, volume, triangles."""
    out = []
    for i in range(n):
        for j in range(n):
            for k in range(n):
                b = trimesh.creation.icosphere(subdivisions=1, radius=size / 2) if (i, j, k) == (1, 1, 1) else \
                    trimesh.creation.box(extents=(size, size, size))
                b.apply_translation(np.array([i, j, k], float) * size + size / 2)
                out.append(SimpleNamespace(id=f"p{i}-{j}-{k}", cell=(i, j, k), mesh=b, volume=float(b.volume),
                                           body_volume=float(b.volume), triangles=len(b.faces)))
    return out


def make_report(pieces):
    # pieces without joints: a jointless puzzle is only a sound build with joints.style none
    return {"volpuzzle_version": "0.1.0", "spec": {"name": "cubes", "grid": [2, 2, 2], "joints": {"style": "none"}},
            "model": {"volume_mm3": 8000.0, "bbox_mm": [[0, 0, 0], [20, 20, 20]], "handedness": "right"},
            "checks": check_pieces([(p.id, p.mesh) for p in pieces], sum(p.volume for p in pieces)),
            "joints": [], "plates": [], "timings_s": {"compose": 0.5}}


@pytest.fixture(scope="module")
def pieces():
    return make_pieces()


def leftovers(parent):
    return sorted(p.name for p in parent.iterdir() if p.name.startswith("."))


@pytest.mark.parametrize("fmt", ["stl", "3mf"])
def test_write_build_files_read_back(tmp_path, pieces, fmt):
    dowel = trimesh.creation.cylinder(radius=2, height=10, sections=16)
    target = tmp_path / "sub" / "cubes"
    report = make_report(pieces)
    for p in pieces:
        p.mesh._cache.clear()
    out = write_build(target, pieces, report, fmt=fmt, dowels=[("dowel-00", dowel)])
    assert out == target and target.is_dir() and leftovers(target.parent) == []
    # writing leaves no triangles cached on the pieces (at 1024 pieces they would be ~200 MB held to the end)
    assert not any("triangles" in p.mesh._cache for p in pieces)
    names = sorted(str(p.relative_to(target)) for p in target.rglob("*") if p.is_file())
    assert names == sorted([f"pieces/{p.id}.{fmt}" for p in pieces]
                           + [f"dowels/dowel-00.{fmt}", "instructions.html", "puzzle.3mf", "report.json",
                              "report.md", ".volpuzzle"])
    for p in pieces:
        path = target / "pieces" / f"{p.id}.{fmt}"
        if fmt == "stl":
            mesh = trimesh.load_mesh(path)
        else:
            ((name, v, f, rgb),) = read_3mf(path, strict=True)
            assert name == p.id and rgb is not None
            mesh = trimesh.Trimesh(v, f)
        assert closed_problem(mesh) is None
        assert mesh.volume == pytest.approx(p.volume, rel=1e-5)
    report = json.loads((target / "report.json").read_text(encoding="utf-8"))
    assert [e["id"] for e in report["pieces"]] == [p.id for p in pieces]
    assert report["pieces"][0]["file"] == f"pieces/p0-0-0.{fmt}"
    assert report["dowels"][0]["file"] == f"dowels/dowel-00.{fmt}"
    assert report["checks"]["passed"] is True and "export" in report["timings_s"]
    md = (target / "report.md").read_text(encoding="utf-8")
    assert "| p1-1-1 |" in md and "## Checks: passed" in md
    # `volpuzzle check DIR` verifies the folder from its files alone
    assert check_directory(target)["passed"]


def test_check_directory_names_a_missing_piece(tmp_path, pieces):
    target = write_build(tmp_path / "c", pieces, make_report(pieces))
    (target / "pieces" / "p1-0-0.stl").unlink()
    with pytest.raises(GeometryError, match=r"c failed its own checks: missing piece file pieces/p1-0-0.stl"):
        check_directory(target)
    checks = check_directory(target, raise_on_failure=False)
    assert checks["missing_files"] == ["pieces/p1-0-0.stl"] and not checks["passed"]


def test_puzzle_3mf_strict_with_colours(tmp_path, pieces):
    target = write_build(tmp_path / "c", pieces, make_report(pieces))
    objs = read_3mf(target / "puzzle.3mf", strict=True)
    assert [o[0] for o in objs] == [p.id for p in pieces]
    assert np.array_equal(np.array([o[3] for o in objs]), piece_colors(len(pieces)))
    for (_, v, f, _), p in zip(objs, pieces, strict=True):
        assert np.allclose(trimesh.Trimesh(v, f).bounds, p.mesh.bounds, atol=1e-4)  # assembled in place


def test_existing_target_needs_force(tmp_path, pieces):
    target = write_build(tmp_path / "c", pieces[:2], make_report(pieces[:2]))
    before = {p: p.read_bytes() for p in target.rglob("*") if p.is_file()}
    with pytest.raises(ExportError, match="exists; use --force to replace it"):
        write_build(target, pieces, make_report(pieces))
    assert {p: p.read_bytes() for p in target.rglob("*") if p.is_file()} == before
    write_build(target, pieces, make_report(pieces), force=True)
    assert len(list((target / "pieces").iterdir())) == len(pieces)
    assert leftovers(tmp_path) == []


def test_force_refuses_a_foreign_folder(tmp_path, pieces):
    (tmp_path / "home").mkdir()
    (tmp_path / "home" / "thesis.tex").write_text("precious")
    with pytest.raises(ExportError, match="not a volpuzzle output folder"):
        write_build(tmp_path / "home", pieces, make_report(pieces), force=True)
    assert (tmp_path / "home" / "thesis.tex").read_text() == "precious"


def test_an_output_place_that_cannot_be_written_is_refused_before_the_build_begins(tmp_path, monkeypatch):
    # a read-only disk or someone else's folder: said at once, not after the whole build (root may write anywhere,
    # so the test denies the folder through os.access, which is what is asked)
    import os

    import volpuzzle
    from volpuzzle import pipeline

    locked = tmp_path / "locked"
    locked.mkdir()
    real = os.access

    def access(path, mode, **kw):
        return False if Path(path) == locked else real(path, mode, **kw)

    monkeypatch.setattr(os, "access", access)
    monkeypatch.setattr(pipeline, "prepare", lambda *_a, **_k: pytest.fail("the build began"))
    spec = Path(__file__).resolve().parent.parent / "specs" / "quarter-torus.yaml"
    with pytest.raises(ExportError, match=f"cannot create the output folder: {locked} is not writable"):
        volpuzzle.build(spec, output_dir=locked / "new" / "qt", jobs=1)
    assert list(locked.iterdir()) == []


def test_failure_midway_leaves_nothing(tmp_path, pieces, monkeypatch):
    def boom(*_args, **_kwargs):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(export_mod, "render_report_md", boom)
    with pytest.raises(ExportError, match="disk on fire"):
        write_build(tmp_path / "c", pieces, make_report(pieces))
    assert list(tmp_path.iterdir()) == []


def test_failure_with_force_keeps_the_old_output(tmp_path, pieces, monkeypatch):
    target = write_build(tmp_path / "c", pieces, make_report(pieces))
    old = (target / "report.json").read_bytes()
    monkeypatch.setattr(export_mod, "write_3mf", lambda *_a, **_k: (_ for _ in ()).throw(OSError("full")))
    with pytest.raises(ExportError, match="full"):
        write_build(target, pieces, make_report(pieces), force=True)
    assert (target / "report.json").read_bytes() == old and leftovers(tmp_path) == []


def test_3mf_extras_are_written_off_the_main_thread_and_their_failure_leaves_nothing(tmp_path, pieces):
    import threading

    threads = {}

    def plate(path):
        threads["plate"] = threading.current_thread() is threading.main_thread()
        m = pieces[0].mesh
        write_3mf(path, [("p0-0-0", m.vertices, m.faces, (10, 20, 30), None)])

    def picture(path):
        threads["picture"] = threading.current_thread() is threading.main_thread()
        path.write_bytes(b"png")

    extras = {"plates/plate-01.3mf": plate, "preview.png": picture}
    target = write_build(tmp_path / "c", pieces, make_report(pieces), extras=extras)
    assert threads == {"plate": False, "picture": True}
    assert [o[0] for o in read_3mf(target / "plates" / "plate-01.3mf", strict=True)] == ["p0-0-0"]
    assert json.loads((target / "report.json").read_text(encoding="utf-8"))["preview"] == "preview.png"

    def lost(_path):
        raise OSError("plate lost")

    with pytest.raises(ExportError, match="plate lost"):
        write_build(tmp_path / "d", pieces, make_report(pieces), extras={**extras, "plates/plate-01.3mf": lost})
    assert not (tmp_path / "d").exists() and leftovers(tmp_path) == []


@pytest.mark.parametrize("fmt", ["stl", "3mf"])
def test_identical_input_identical_bytes(tmp_path, pieces, fmt):
    a = write_build(tmp_path / "a", pieces, make_report(pieces), fmt=fmt)
    b = write_build(tmp_path / "b", make_pieces(), make_report(pieces), fmt=fmt)
    for p in pieces:
        rel = f"pieces/{p.id}.{fmt}"
        assert (a / rel).read_bytes() == (b / rel).read_bytes()
    assert (a / "puzzle.3mf").read_bytes() == (b / "puzzle.3mf").read_bytes()


def test_write_3mf_transform_and_second_material(tmp_path):
    box = trimesh.creation.box(extents=(2, 2, 2))
    t = np.hstack([np.eye(3), [[10], [20], [30]]])
    marks = np.zeros(len(box.faces), int)
    marks[:4] = 1
    path = write_3mf(tmp_path / "m.3mf", [("b", box.vertices, box.faces, (1, 2, 3), t),
                                          ("c", box.vertices, box.faces, None, None)], materials=[marks, None])
    (n1, v1, _, rgb1), (n2, v2, _, rgb2) = read_3mf(path, strict=True)
    assert (n1, n2) == ("b", "c") and rgb1.tolist() == [1, 2, 3] and rgb2 is None
    assert np.allclose(v1.mean(axis=0), [10, 20, 30]) and np.allclose(v2.mean(axis=0), 0)


def test_write_3mf_rejects_bad_faces(tmp_path):
    with pytest.raises(ExportError, match=r"m.3mf: object 'x': face indices must lie in \[0, 2\]"):
        write_3mf(tmp_path / "m.3mf", [("x", np.zeros((3, 3)), [[0, 1, 5]], None, None)])


def test_read_3mf_names_the_file(tmp_path):
    bad = tmp_path / "bad.3mf"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ModelError, match="bad.3mf: not a readable 3MF file"):
        read_3mf(bad)
    with pytest.raises(ModelError, match="missing.3mf: no such 3MF file"):
        read_3mf(tmp_path / "missing.3mf")


def test_read_3mf_strict_refuses_what_lax_mode_accepts(tmp_path):
    import zipfile

    box = trimesh.creation.box()
    good = write_3mf(tmp_path / "ok.3mf", [("b", box.vertices, box.faces, (1, 2, 3), None)])
    with zipfile.ZipFile(good) as z:
        parts = {n: z.read(n) for n in z.namelist()}
    parts["3D/3dmodel.model"] = parts["3D/3dmodel.model"].replace(b"<vertex ", b'<vertex q="1" ', 1)
    odd = tmp_path / "odd.3mf"
    with zipfile.ZipFile(odd, "w") as z:
        for name, data in parts.items():
            z.writestr(name, data)
    with pytest.raises(ModelError, match="odd.3mf: not a readable 3MF file.*Invalid Attribute"):
        read_3mf(odd, strict=True)
    assert len(read_3mf(odd, strict=False)) == 1


def test_unknown_format_is_refused(tmp_path, pieces):
    with pytest.raises(ExportError, match="output.format: got 'obj'"):
        write_build(tmp_path / "c", pieces, {}, fmt="obj")


def test_piece_colors_distinct_and_stable():
    c = piece_colors(64)
    assert c.shape == (64, 3) and c.dtype == np.uint8
    assert np.array_equal(c, piece_colors(64)) and np.array_equal(c[:5], piece_colors(5))
    assert len({tuple(x) for x in c}) == 64
    d = np.linalg.norm(c[1:].astype(float) - c[:-1], axis=1)
    assert d.min() > 40  # consecutive pieces (often neighbours) differ visibly


def test_report_piece_entry_and_clean_json(pieces):
    e = clean_json(report_piece_entry(pieces[0], "pieces/p0-0-0.stl"))
    assert e == {"id": "p0-0-0", "cell": [0, 0, 0], "file": "pieces/p0-0-0.stl", "volume_mm3": 1000.0,
                 "bbox_mm": [[0.0, 0.0, 0.0], [10.0, 10.0, 10.0]], "triangles": 12, "plate": None}
    assert clean_json({"a": (np.float32(0.1), np.int64(3), float("nan"), 0.1 + 0.2)}) == {"a": [0.1, 3, None, 0.3]}
    json.dumps(e, allow_nan=False)


def _piece(pid, mesh):
    return SimpleNamespace(id=pid, mesh=mesh)


def test_printable_names_float32_rounding_when_only_the_file_precision_breaks_the_piece():
    # one closed body 1e-6 mm thick at x = 100: float32 (resolution ~8e-6 mm there) folds its two faces together
    box = trimesh.creation.box(extents=(1e-6, 20.0, 20.0))
    box.apply_translation((100.0, 0.0, 0.0))
    assert closed_problem(box) is None
    with pytest.raises(GeometryError, match=r"^p0-0-0: the piece is no longer one closed solid at the float32 "
                                            r"precision .*try a smaller output.tolerance$"):
        export_mod.printable([_piece("p0-0-0", box)])


def test_printable_names_a_piece_whose_own_surface_meets_itself_and_where():
    # two boxes sharing one edge, each with its own vertices (as the engine keeps a pinch): no tolerance mends it
    a = trimesh.creation.box(extents=(10.0, 10.0, 10.0))
    b = a.copy()
    b.apply_translation((10.0, 10.0, 0.0))
    both = trimesh.Trimesh(np.vstack([a.vertices, b.vertices]), np.vstack([a.faces, b.faces + len(a.vertices)]),
                           process=False)
    with pytest.raises(GeometryError) as err:
        export_mod.printable([_piece("p1-0-0", both)])
    msg = str(err.value)
    assert msg.startswith("p1-0-0: the piece's surface meets itself at (5.00, 5.00, ")
    assert "non-manifold edges" in msg and "float32" not in msg
    assert msg.endswith("try other cuts: another grid, splits or model.cage.padding")
