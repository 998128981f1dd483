"""Fuzzing (hypothesis) over report.json for `check` and over the model readers: every outcome is a VolpuzzleError
or success, never another exception, and `check` never opens a file outside its folder."""

import builtins
import json
import os
import shutil

import pytest
import trimesh
from conftest import DATA
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_hostile import _pieces
from test_hostile import _report as _boxes_report

from volpuzzle.check import check_directory
from volpuzzle.errors import VolpuzzleError
from volpuzzle.export import write_build
from volpuzzle.io import load_model
from volpuzzle.io.mesh import read_mesh

FAST = settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fuzz")
    pieces = _pieces()
    report = _boxes_report(pieces)
    out = write_build(tmp / "out", pieces, report)
    outside = tmp / "outside"
    outside.mkdir()
    shutil.copy(out / "pieces" / "p0-0-0.stl", outside / "p0-0-0.stl")
    (out / "pieces" / "link.stl").symlink_to(outside / "p0-0-0.stl")
    return out, outside


_files = st.sampled_from(["pieces/p0-0-0.stl", "pieces/p1-0-0.stl", "pieces/link.stl", "../outside/p0-0-0.stl",
                          "pieces/../../outside/p0-0-0.stl", "OUTSIDE_ABS", "pieces", "", ".", "report.json",
                          "pieces/none.stl", "a\0b", "pieces//p0-0-0.stl", "./pieces/p1-0-0.stl", "C:\\x.stl"])
_scalar = st.one_of(st.none(), st.booleans(), st.integers(-10 ** 40, 10 ** 40), st.floats(allow_nan=True),
                    st.text(max_size=8))
_json = st.recursive(_scalar, lambda kids: st.one_of(st.lists(kids, max_size=3),
                                                     st.dictionaries(st.text(max_size=6), kids, max_size=3)),
                     max_leaves=8)
_piece = st.fixed_dictionaries({"id": st.one_of(st.sampled_from(["p0-0-0", "p1-0-0"]), _scalar),
                                "file": st.one_of(_files, _scalar)})
_joint = st.fixed_dictionaries({
    "pin_piece": st.sampled_from(["p0-0-0", "p1-0-0", 3]), "hole_piece": st.sampled_from(["p0-0-0", "p1-0-0"]),
    "center_mm": st.one_of(st.just([10.0, 5.0, 5.0]), _json), "direction": st.one_of(st.just([1.0, 0, 0]), _json),
    "radius_mm": st.one_of(st.floats(0.1, 3), _scalar), "length_mm": st.one_of(st.floats(0.5, 4), _scalar)})
_report = st.fixed_dictionaries({}, optional={
    "pieces": st.one_of(st.lists(_piece, max_size=3), _json),
    "checks": st.one_of(st.fixed_dictionaries({"expected_volume_mm3": st.one_of(st.just(2000.0), _scalar)}), _json),
    "model": _json, "joints": st.one_of(st.lists(_joint, max_size=2), _json)})


@FAST
@given(report=_report)
def test_check_on_any_report_stays_in_its_folder(base, report):
    out, outside = base
    text = json.dumps(report).replace("OUTSIDE_ABS", str(outside / "p0-0-0.stl").replace("\\", "\\\\"))
    (out / "report.json").write_text(text)
    opened = []
    real_open, real_os_open = builtins.open, os.open

    def spy_open(file, *a, **k):
        opened.append(os.fspath(file) if isinstance(file, (str, os.PathLike)) else None)
        return real_open(file, *a, **k)

    def spy_os_open(path, *a, dir_fd=None, **k):
        if dir_fd is None:
            opened.append(os.fspath(path))
        else:
            opened.append(os.path.join(os.readlink(f"/proc/self/fd/{dir_fd}"), os.fspath(path)))
        return real_os_open(path, *a, dir_fd=dir_fd, **k)

    builtins.open, os.open = spy_open, spy_os_open
    try:
        check_directory(out, raise_on_failure=False)
    except VolpuzzleError:
        pass
    finally:
        builtins.open, os.open = real_open, real_os_open
    for p in opened:
        if p is None or p.startswith(("/proc/", "/dev/")) or "site-packages" in p or p.endswith(".py"):
            continue
        real = os.path.realpath(p)
        assert not real.startswith(os.path.realpath(outside)), f"read {p} outside the folder"


_SEEDS = {name: (DATA / name).read_bytes() for name in
          ("irit_bent_pipe.itd", "gismo_cylinder.xml", "geomdl_twisted_pipe.json")}


@st.composite
def _mutated(draw):
    name = draw(st.sampled_from(sorted(_SEEDS)))
    data = bytearray(_SEEDS[name])
    for _ in range(draw(st.integers(1, 6))):
        kind = draw(st.sampled_from(["flip", "cut", "insert", "number"]))
        at = draw(st.integers(0, max(len(data) - 1, 0)))
        if kind == "flip" and data:
            data[at] = draw(st.integers(0, 255))
        elif kind == "cut":
            del data[at:at + draw(st.integers(1, 400))]
        elif kind == "insert":
            data[at:at] = draw(st.sampled_from([b"[", b"]", b"<", b"1e308 ", b"-", b"99999999999999999999", b"\0",
                                                b"<!ENTITY e 'x'>", b"nan", b'"', b"{", b"}"]))
        else:
            data[at:at] = str(draw(st.one_of(st.integers(-10 ** 30, 10 ** 30), st.floats()))).encode()
    return name, bytes(data)


@FAST
@given(case=_mutated())
def test_model_readers_on_mutated_files(tmp_path_factory, case):
    name, data = case
    path = tmp_path_factory.mktemp("m") / name
    path.write_bytes(data)
    try:
        load_model(path)
    except VolpuzzleError:
        pass


_STL = trimesh.exchange.stl.export_stl(trimesh.creation.box(extents=(10, 10, 10)))
_ASCII = trimesh.exchange.stl.export_stl_ascii(trimesh.creation.box(extents=(10, 10, 10))).encode()


@FAST
@given(data=st.one_of(st.binary(max_size=300), st.sampled_from([_STL, _ASCII]).flatmap(
    lambda seed: st.tuples(st.integers(0, len(seed)), st.binary(max_size=20), st.integers(0, 60)).map(
        lambda t: seed[:t[0]] + t[1] + seed[t[0] + t[2]:]))),
    ext=st.sampled_from([".stl", ".off", ".obj", ".ply"]))
def test_mesh_reader_on_any_bytes(tmp_path_factory, data, ext):
    path = tmp_path_factory.mktemp("mesh") / f"m{ext}"
    path.write_bytes(data)
    try:
        read_mesh(path)
    except VolpuzzleError:
        pass
