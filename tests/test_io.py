"""Model readers and writer: reference volumes, agreement between formats, round trips, and one test per error."""

import base64
import csv
import json
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA
from hypothesis import given, settings
from hypothesis import strategies as st

from volpuzzle.errors import ModelError, VolpuzzleError
from volpuzzle.io import load_model, load_model_with_meta, read_patches, save_model
from volpuzzle.spline.volume import Volume

REFERENCE = list(csv.DictReader(open(DATA / "REFERENCE_VALUES.tsv"), delimiter="\t"))


def ref_path(row):
    return DATA / Path(row["file_here"]).name


def det_j(vol, n=200, seed=0):
    rng = np.random.default_rng(seed)
    lo, hi = vol.domain_array
    uvw = lo + (hi - lo) * rng.uniform(0.02, 0.98, (n, 3))
    return np.linalg.det(vol.derivatives(uvw))


def unit_cube(**extra):
    cps = np.stack(np.meshgrid([0.0, 1.0], [0.0, 2.0], [0.0, 3.0], indexing="ij"), -1)
    d = {"format": "volpuzzle-nurbs", "version": 1, "degrees": [1, 1, 1], "knots": [[0, 0, 1, 1]] * 3,
         "control_points": cps.tolist(), "units": "mm"}
    d.update(extra)
    return d


def write(tmp_path, name, content):
    p = tmp_path / name
    if isinstance(content, (dict, list)):
        content = json.dumps(content)
    p.write_text(content)
    return p


def model_error(path, patch=0):
    with pytest.raises(ModelError) as e:
        load_model(path, patch=patch)
    msg = str(e.value)
    assert msg.startswith(str(path)), msg  # every message names the file
    assert "Traceback" not in msg and "\n" not in msg
    return msg


# --- reference files ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("row", REFERENCE, ids=lambda r: Path(r["file_here"]).stem)
def test_reference_handedness_and_bbox(row):
    vols = read_patches(ref_path(row))
    assert len(vols) == int(row["patches"])
    pos, neg = (int(x) for x in row["signs(+/-)"].split("/"))
    signs = []
    for v in vols:
        d = det_j(v)
        assert np.all(d > 0) or np.all(d < 0), "a reference patch folds"
        signs.append(d[0] > 0)
    assert (sum(signs), len(signs) - sum(signs)) == (pos, neg)
    # The table's box is of the geometry, sampled; compare with a 21^3 sample of each patch.
    xyz = np.concatenate([v.evaluate_grid(*(np.linspace(*v.domain[a], 21) for a in range(3))).reshape(-1, 3)
                          for v in vols])
    ref_lo, ref_hi = np.array(json.loads(row["geom_bbox_min"])), np.array(json.loads(row["geom_bbox_max"]))
    tol = 2e-3 * np.linalg.norm(ref_hi - ref_lo)
    np.testing.assert_allclose(xyz.min(0), ref_lo, atol=tol)
    np.testing.assert_allclose(xyz.max(0), ref_hi, atol=tol)


@pytest.mark.parametrize("row", REFERENCE, ids=lambda r: Path(r["file_here"]).stem)
def test_reference_volume(row):
    from volpuzzle.spline import measure

    total = sum(abs(float(measure.volume(v))) for v in read_patches(ref_path(row)))
    ref = float(row["sum_abs_volume"])
    # The table prints 6 decimals (half a unit: 5e-7). The spring's reference is under-integrated: it equals a
    # 6-point Gauss rule per knot span; the converged integral is 355.3057584 (rel. 1.3e-6 above it).
    rel = 1.5e-6 if "spring" in row["file_here"] else 1e-6
    assert abs(total - ref) <= rel * ref + 5e-7, (total, ref)


def test_water_passage_patches_in_file_order():
    vols, meta = read_patches(DATA / "gismo_water_passage_3p.xml"), load_model_with_meta(
        DATA / "gismo_water_passage_3p.xml", patch=2)[1]
    assert meta["patches"] == 3 and meta["format"] == "gismo-xml" and meta["units"] is None
    assert vols[0].control_points[0, 0, 0].tolist() == [177.987, 129.308, 71.002]
    assert vols[1].control_points[0, 0, 0].tolist() == [158.788, 60.214, 24.1898]
    assert vols[2].control_points[0, 0, 0].tolist() == [129.781, -104.208, -34.2758]


def test_three_formats_of_the_twisted_pipe_agree():
    uvw = np.random.default_rng(3).uniform(0, 1, (500, 3))
    ref = load_model(DATA / "gismo_twisted_pipe.xml")
    for name in ("irit_twisted_pipe.itd", "geomdl_twisted_pipe.json"):
        np.testing.assert_allclose(load_model(DATA / name).evaluate(uvw), ref.evaluate(uvw), rtol=0, atol=1e-12)


def test_irit_rational_bent_pipe_agrees_with_gismo():
    a, b = load_model(DATA / "gismo_bent_pipe.xml"), load_model(DATA / "irit_bent_pipe.itd")
    assert b.is_rational
    uvw = np.random.default_rng(4).uniform(0, 1, (500, 3)) * [1, 1, 2]
    np.testing.assert_allclose(b.evaluate(uvw), a.evaluate(uvw), rtol=0, atol=1e-12)


def test_geomdl_reader_matches_geomdl_evaluation_rational(tmp_path):
    from geomdl import NURBS, exchange

    rng = np.random.default_rng(5)
    n, p = (4, 3, 5), (2, 1, 3)
    vol = NURBS.Volume()
    vol.degree_u, vol.degree_v, vol.degree_w = p
    vol.ctrlpts_size_u, vol.ctrlpts_size_v, vol.ctrlpts_size_w = n
    pts = rng.normal(size=(np.prod(n), 3))
    w = rng.uniform(0.5, 2.0, np.prod(n))
    vol.ctrlptsw = [list(q * wi) + [wi] for q, wi in zip(pts, w, strict=True)]
    vol.knotvector_u, vol.knotvector_v, vol.knotvector_w = (
        [0.0] * (pk + 1) + list(np.linspace(0, 1, nk - pk + 1)[1:-1]) + [1.0] * (pk + 1)
        for nk, pk in zip(n, p, strict=True))
    exchange.export_json(vol, str(tmp_path / "g.json"))
    mine = load_model(tmp_path / "g.json")
    uvw = rng.uniform(0, 1, (20, 3))
    theirs = np.array([vol.evaluate_single(tuple(t)) for t in uvw])
    np.testing.assert_allclose(mine.evaluate(uvw), theirs, atol=1e-12)


def test_gismo_comment_before_declaration(tmp_path):
    text = "<!-- written by hand -->\n" + (DATA / "gismo_twisted_pipe.xml").read_text()
    assert text.index("<?xml") > 0
    v = load_model(write(tmp_path, "c.xml", text))
    assert np.array_equal(v.control_points, load_model(DATA / "gismo_twisted_pipe.xml").control_points)


def test_gismo_base64_coefficients():
    v, meta = load_model_with_meta(DATA / "gismo_b64_cube.xml")
    assert meta["patches"] == 1 and v.is_rational and v.shape == (7, 7, 8) and v.degrees == (2, 2, 3)
    assert v.domain == ((0.0, 1.0), (0.0, 1.0), (0.0, 1.0))
    assert np.all(np.isfinite(v.evaluate(np.full((1, 3), 0.5))))


def test_gismo_base64_float32_equals_ascii(tmp_path):
    text = (DATA / "gismo_twisted_pipe.xml").read_text()
    m = re.search(r'<coefs geoDim="3">(.*?)</coefs>', text, re.S)
    nums = np.array(m.group(1).split(), dtype=float)
    b64 = base64.b64encode(nums.astype("<f4").tobytes()).decode()
    text = text.replace(m.group(0), f'<coefs geoDim="3" format="B64Float32">{b64}</coefs>')
    a, b = load_model(DATA / "gismo_twisted_pipe.xml"), load_model(write(tmp_path, "f32.xml", text))
    np.testing.assert_allclose(b.control_points, a.control_points, rtol=1e-6, atol=1e-7)


def test_gismo_multipatch_ids_give_the_patch_order(tmp_path):
    text = (DATA / "gismo_water_passage_3p.xml").read_text()
    text = re.sub(r'<patches type="id_range">0 2</patches>', '<patches type="id_index">2 0 1</patches>', text)
    vols = read_patches(write(tmp_path, "mp.xml", text))
    ref = read_patches(DATA / "gismo_water_passage_3p.xml")
    assert [np.array_equal(a.control_points, b.control_points)
            for a, b in zip(vols, [ref[2], ref[0], ref[1]], strict=True)] \
        == [True] * 3


def test_gismo_knots_off_unit_interval_and_unclamped(tmp_path):
    # A floating cubic knot vector is converted to the clamped one giving the same volume on [3, 6].
    rng = np.random.default_rng(6)
    cps = rng.normal(size=(6, 2, 2, 3))
    coefs = " ".join(repr(float(x)) for x in cps.transpose(2, 1, 0, 3).ravel())
    text = f"""<xml><Geometry type="TensorBSpline3" id="0"><Basis type="TensorBSplineBasis3">
      <Basis type="BSplineBasis" index="0"><KnotVector degree="3">0 1 2 3 4 5 6 7 8 9</KnotVector></Basis>
      <Basis type="BSplineBasis" index="1"><KnotVector degree="1">-2 -2 5 5</KnotVector></Basis>
      <Basis type="BSplineBasis" index="2"><KnotVector degree="1">10 10 11 11</KnotVector></Basis>
      </Basis><coefs geoDim="3">{coefs}</coefs></Geometry></xml>"""
    v = load_model(write(tmp_path, "float.xml", text))
    assert v.domain == ((3.0, 6.0), (-2.0, 5.0), (10.0, 11.0))
    t = np.linspace(3, 6, 13)
    uvw = np.stack([t, np.full_like(t, -2.0), np.full_like(t, 10.0)], 1)
    from volpuzzle.spline import basis

    span = basis.find_span(np.arange(10.0), 3, t)
    nb = basis.basis_functions(np.arange(10.0), 3, t, span)
    direct = np.array([nb[i] @ cps[span[i] - 3:span[i] + 1, 0, 0] for i in range(len(t))])
    np.testing.assert_allclose(v.evaluate(uvw), direct, atol=1e-12)


def test_irit_bezier_trivariate(tmp_path):
    rng = np.random.default_rng(7)
    cps = rng.normal(size=(3, 2, 2, 3))
    pts = "\n".join("[" + " ".join(repr(float(x)) for x in p) + "]" for p in cps.transpose(2, 1, 0, 3).reshape(-1, 3))
    v = load_model(write(tmp_path, "b.itd", f"[OBJECT BEZ\n [TRIVAR BEZIER 3 2 2 E3\n{pts}\n ]\n]\n"))
    assert v.degrees == (2, 1, 1) and v.domain == ((0.0, 1.0),) * 3
    np.testing.assert_array_equal(v.control_points, cps)


def test_irit_periodic_knot_vector_is_unrolled_and_clamped(tmp_path):
    # KVP of order 3 over 5 points: 5 + 2*3 - 1 = 10 knots; the closed direction comes back to its start.
    rng = np.random.default_rng(8)
    cps = rng.normal(size=(5, 2, 2, 3))
    pts = "\n".join("[" + " ".join(repr(float(x)) for x in p) + "]" for p in cps.transpose(2, 1, 0, 3).reshape(-1, 3))
    text = (f"[OBJECT RING [color 4]\n [TRIVAR BSPLINE 5 2 2 3 2 2 E3\n [KVP 0 1 2 3 4 5 6 7 8 9]\n"
            f" [KV 0 0 1 1]\n [KV 0 0 1 1]\n{pts}\n ]\n]\n"
            "[OBJECT OTHER [CURVE BSPLINE 2 2 E2 [KV 0 0 1 1] [0 0] [1 1]]]\n")
    v, meta = load_model_with_meta(write(tmp_path, "p.itd", text))
    assert v.domain[0] == (2.0, 7.0) and meta["periodic_knots"] == [["u"]]
    vw = np.random.default_rng(9).uniform(0, 1, (50, 2))
    lo = np.c_[np.full(50, 2.0), vw]
    hi = np.c_[np.full(50, 7.0), vw]
    np.testing.assert_allclose(v.evaluate(lo), v.evaluate(hi), atol=1e-12)


def test_detection_by_content_not_extension(tmp_path):
    text = (DATA / "irit_twisted_pipe.itd").read_text()
    v, meta = load_model_with_meta(write(tmp_path, "pipe.txt", text))
    assert meta["format"] == "irit-itd" and v.shape == (10, 4, 4)
    _, meta = load_model_with_meta(write(tmp_path, "cube.xml", json.dumps(unit_cube())))
    assert meta["format"] == "volpuzzle-json" and meta["units"] == "mm"


def test_volpuzzle_json_multi_patch_extension(tmp_path):
    a = {k: v for k, v in unit_cube().items() if k in ("degrees", "knots", "control_points")}
    b = dict(a, weights=np.full((2, 2, 2), 2.0).tolist())
    p = write(tmp_path, "two.json", {"format": "volpuzzle-nurbs", "version": 1, "units": "cm", "patches": [a, b]})
    vols, meta = read_patches(p), load_model_with_meta(p, patch=1)[1]
    assert len(vols) == 2 and vols[1].is_rational and meta["units"] == "cm"


# --- writer -------------------------------------------------------------------------------------------------------
@st.composite
def volumes(draw):
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    degrees = [draw(st.integers(1, 3)) for _ in range(3)]
    sizes = [p + 1 + draw(st.integers(0, 3)) for p in degrees]
    knots = []
    for p, n in zip(degrees, sizes, strict=True):
        inner = np.sort(rng.uniform(-1, 3, n - p - 1))
        knots.append(np.r_[[-1.0] * (p + 1), inner, [3.0] * (p + 1)])
    cps = rng.normal(size=tuple(sizes) + (3,)) * 10 ** rng.uniform(-3, 3)
    w = rng.uniform(0.1, 10, sizes) if draw(st.booleans()) else None
    return Volume(degrees, knots, cps, w)


@settings(max_examples=25, deadline=None)
@given(vol=volumes())
def test_save_load_round_trip_is_exact(tmp_path_factory, vol):
    d = tmp_path_factory.mktemp("rt")
    save_model(vol, d / "a.json", units="in")
    back, meta = load_model_with_meta(d / "a.json")
    assert meta["units"] == "in" and meta["format"] == "volpuzzle-json"
    assert back.degrees == vol.degrees
    assert all(np.array_equal(a, b) for a, b in zip(back.knots, vol.knots, strict=True))
    assert np.array_equal(back.control_points, vol.control_points)
    assert (back.weights is None) == (vol.weights is None)
    if vol.weights is not None:
        assert np.array_equal(back.weights, vol.weights)
    save_model(back, d / "b.json", units="in")
    assert (d / "a.json").read_bytes() == (d / "b.json").read_bytes()  # deterministic


def test_saved_file_follows_the_spec(tmp_path):
    vol = load_model(DATA / "gismo_bent_pipe.xml")
    save_model(vol, tmp_path / "bent.json")
    d = json.loads((tmp_path / "bent.json").read_text())
    assert d["format"] == "volpuzzle-nurbs" and d["version"] == 1 and d["units"] == "mm"
    assert np.array(d["control_points"]).shape == (9, 2, 5, 3) and np.array(d["weights"]).shape == (9, 2, 5)
    assert d["degrees"] == [2, 1, 2] and [len(k) for k in d["knots"]] == [12, 4, 8]


# --- errors: one test per message ---------------------------------------------------------------------------------
def test_error_knot_vector_wrong_length(tmp_path):
    msg = model_error(write(tmp_path, "m.json", unit_cube(knots=[[0, 0, 1], [0, 0, 1, 1], [0, 0, 1, 1]])))
    assert "knots[0] (u)" in msg and "length 3" in msg and "expected 4" in msg


def test_error_knot_vector_decreasing(tmp_path):
    msg = model_error(write(tmp_path, "m.json", unit_cube(knots=[[0, 0, 1, 1], [0, 0, 1, 1], [0, 1, 0, 1]])))
    assert "knots[2] (w)" in msg and "not non-decreasing" in msg


def test_error_weight_not_positive(tmp_path):
    w = np.ones((2, 2, 2))
    w[1, 0, 1] = -0.5
    msg = model_error(write(tmp_path, "m.json", unit_cube(weights=w.tolist())))
    assert "weights" in msg and "> 0" in msg and "[1, 0, 1]" in msg


def test_error_irit_weight_not_positive(tmp_path):
    text = (DATA / "irit_bent_pipe.itd").read_text().replace("[1.0 1.0 0.0 3.0]", "[0.0 1.0 0.0 3.0]", 1)
    msg = model_error(write(tmp_path, "m.itd", text))
    assert "weights" in msg and "> 0" in msg and "got 0" in msg


def test_error_nan_coordinate(tmp_path):
    cps = np.array(unit_cube()["control_points"])
    cps[0, 1, 1, 2] = np.nan
    msg = model_error(write(tmp_path, "m.json", unit_cube(control_points=cps.tolist())))
    assert "control_points" in msg and "NaN or infinity" in msg and "[0, 1, 1]" in msg


def test_error_wrong_control_point_count_gismo(tmp_path):
    text = (DATA / "gismo_quarter_annulus3d.xml").read_text().replace("0 2 1 \n</coefs>", "</coefs>")
    msg = model_error(write(tmp_path, "m.xml", text))
    assert "coefs" in msg and "2 x 3 x 2 = 12 control points" in msg and "got 33 numbers" in msg


def test_error_wrong_control_point_count_geomdl(tmp_path):
    d = json.loads((DATA / "geomdl_twisted_pipe.json").read_text())
    d["shape"]["data"][0]["size_u"] = 9
    msg = model_error(write(tmp_path, "m.json", d))
    assert "control_points.points" in msg and "9 x 4 x 4 = 144" in msg


def test_error_wrong_control_point_count_irit(tmp_path):
    text = (DATA / "irit_twisted_pipe.itd").read_text().replace("[-0.5 0.245798449741138 -0.067312253486936]", "", 1)
    msg = model_error(write(tmp_path, "m.itd", text))
    assert "control points" in msg and "10 x 4 x 4 = 160 points, got 159" in msg


def test_error_control_points_ragged(tmp_path):
    msg = model_error(write(tmp_path, "m.json", unit_cube(control_points=[[[[0, 0, 0]]], [[[0, 0]]]])))
    assert "control_points" in msg and "rectangular" in msg


def test_error_truncated_json(tmp_path):
    msg = model_error(write(tmp_path, "m.json", json.dumps(unit_cube())[:120]))
    assert "truncated JSON" in msg and "line 1" in msg


def test_error_invalid_json(tmp_path):
    msg = model_error(write(tmp_path, "m.json", '{"format": "volpuzzle-nurbs", version: 1}'))
    assert "invalid JSON" in msg and "column" in msg


def test_error_json_not_a_volume_model(tmp_path):
    msg = model_error(write(tmp_path, "m.json", {"name": "cube"}))
    assert "volpuzzle-nurbs" in msg and '"shape"' in msg


def test_error_wrong_version(tmp_path):
    msg = model_error(write(tmp_path, "m.json", unit_cube(version=2)))
    assert "version" in msg and "expected 1, got 2" in msg


def test_error_bad_units(tmp_path):
    msg = model_error(write(tmp_path, "m.json", unit_cube(units="ft")))
    assert "units" in msg and "mm, cm, m, in" in msg and "'ft'" in msg


def test_error_missing_degrees(tmp_path):
    d = unit_cube()
    del d["degrees"]
    msg = model_error(write(tmp_path, "m.json", d))
    assert "degrees" in msg and "missing" in msg


def test_error_truncated_xml(tmp_path):
    msg = model_error(write(tmp_path, "m.xml", (DATA / "gismo_twisted_pipe.xml").read_text()[:900]))
    assert "truncated XML" in msg and "line" in msg


def test_error_xml_entities_refused(tmp_path):
    text = '<?xml version="1.0"?><!DOCTYPE xml [<!ENTITY a "aaaa">]><xml>&a;</xml>'
    msg = model_error(write(tmp_path, "m.xml", text))
    assert "ENTITY" in msg


def test_error_truncated_irit(tmp_path):
    msg = model_error(write(tmp_path, "m.itd", (DATA / "irit_twisted_pipe.itd").read_text()[:3000]))
    assert "truncated IRIT" in msg and "never closed" in msg


def test_error_no_volume_in_gismo_file(tmp_path):
    msg = model_error(write(tmp_path, "m.xml", '<xml><Geometry type="TensorBSpline2" id="0"/></xml>'))
    assert "no volume" in msg and "TensorBSpline2" in msg and "TensorBSpline3" in msg


def test_error_no_volume_in_irit_file(tmp_path):
    msg = model_error(write(tmp_path, "m.itd", "[OBJECT C [CURVE BSPLINE 2 2 E2 [KV 0 0 1 1] [0 0] [1 1]]]\n"))
    assert "no volume" in msg and "TRIVAR BSPLINE" in msg


def test_error_no_volume_in_geomdl_file(tmp_path):
    msg = model_error(write(tmp_path, "m.json", {"shape": {"type": "surface", "count": 0, "data": []}}))
    assert "shape.type" in msg and "no volume" in msg and "'surface'" in msg


def test_error_scalar_irit_trivariate(tmp_path):
    pts = " ".join(f"[{i}]" for i in range(8))
    msg = model_error(write(tmp_path, "m.itd", f"[OBJECT S [TRIVAR BEZIER 2 2 2 E1 {pts}]]\n"))
    assert "E1" in msg and "scalar" in msg and "E3 or P3" in msg


def test_error_scalar_gismo_trivariate(tmp_path):
    text = (DATA / "gismo_twisted_pipe.xml").read_text().replace('geoDim="3"', 'geoDim="1"')
    msg = model_error(write(tmp_path, "m.xml", text))
    assert "geoDim" in msg and "scalar" in msg and "expected geoDim 3" in msg


def test_error_thb_spline():
    msg = model_error(DATA / "gismo_thbcube.xml")
    assert "THBSpline3" in msg and "TensorBSpline3, TensorNurbs3" in msg


def test_error_irit_periodic_knot_count(tmp_path):
    text = "[OBJECT [TRIVAR BSPLINE 2 2 2 2 2 2 E3 [KVP 0 1 2] [KV 0 0 1 1] [KV 0 0 1 1]" + " [0 0 0]" * 8 + "]]"
    msg = model_error(write(tmp_path, "m.itd", text))
    assert "KVP u" in msg and "needs 5 knots, got 3" in msg


def test_error_missing_file(tmp_path):
    msg = model_error(tmp_path / "nope.json")
    assert "no such file" in msg


def test_error_directory(tmp_path):
    msg = model_error(tmp_path)
    assert "is a directory" in msg


def test_error_empty_file(tmp_path):
    msg = model_error(write(tmp_path, "m.xml", "  \n"))
    assert "empty" in msg


def test_error_unrecognised_format(tmp_path):
    msg = model_error(write(tmp_path, "m.step", "ISO-10303-21;"))
    assert "unrecognised model format" in msg and ".itd" in msg


def test_error_a_mesh_is_named_a_mesh(tmp_path):
    # `volpuzzle info bunny.off` is what a new user tries first: say it is a mesh and how to use one
    msg = model_error(write(tmp_path, "m.off", "OFF\n0 0 0\n"))
    assert "m.off: a .off file is a triangle mesh, not a volume model" in msg
    assert "model: {mesh: FILE" in msg and ".itd" in msg


def test_error_patch_out_of_range():
    msg = model_error(DATA / "gismo_water_passage_3p.xml", patch=3)
    assert "patch" in msg and "3 patches" in msg and "0 to 2" in msg


def test_errors_are_volpuzzle_errors():
    assert issubclass(ModelError, VolpuzzleError)


def test_error_patch_not_an_integer():
    msg = model_error(DATA / "gismo_water_passage_3p.xml", patch="1")
    assert "patch" in msg and "expected an integer from 0 to 2" in msg


def test_error_xml_root_not_gismo(tmp_path):
    msg = model_error(write(tmp_path, "m.xml", "<svg><g/></svg>"))
    assert "<xml> root" in msg and "<svg>" in msg


def test_error_scalar_geomdl_volume(tmp_path):
    d = json.loads((DATA / "geomdl_twisted_pipe.json").read_text())
    d["shape"]["data"][0]["dimension"] = 1
    msg = model_error(write(tmp_path, "m.json", d))
    assert "dimension" in msg and "scalar" in msg and "expected dimension 3" in msg


def test_error_gismo_unknown_number_format(tmp_path):
    text = (DATA / "gismo_twisted_pipe.xml").read_text().replace('geoDim="3"', 'geoDim="3" format="B64Float16"')
    msg = model_error(write(tmp_path, "m.xml", text))
    assert "coefs" in msg and "'B64Float16'" in msg and "B64Float64" in msg
