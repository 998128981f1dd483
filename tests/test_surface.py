"""Surface readers, the Surface type and the thick shell (issue 11)."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from volpuzzle.errors import ModelError
from volpuzzle.io import load_surface, load_surface_with_meta
from volpuzzle.shell import make_shell, scale_to_mm, tightest_inner_bend
from volpuzzle.spline.measure import volume as volume_of
from volpuzzle.spline.surface import Surface

DATA = Path(__file__).parent / "data" / "surfaces"


def _small(rational=True):
    """A hand-made bicubic x biquadratic surface, 5 x 4 control points, one interior knot per direction."""
    rng = np.random.default_rng(4)
    ku = np.array([0, 0, 0, 0, 0.4, 1, 1, 1, 1.0])
    kv = np.array([0, 0, 0, 0.5, 1, 1, 1.0])
    g = np.stack(np.meshgrid(np.linspace(0, 4, 5), np.linspace(0, 3, 4), indexing="ij"), -1)
    cps = np.concatenate([g, rng.uniform(-0.5, 0.5, (5, 4, 1))], -1)
    w = rng.uniform(0.6, 1.6, (5, 4)) if rational else None
    return Surface((3, 2), (ku, kv), cps, w)


def _reference(s, uv):
    """Points by the definition: sum of basis times weighted points over the sum of basis times weights."""
    from volpuzzle.spline.basis import basis_matrix

    bu = basis_matrix(s.knots[0], s.degrees[0], uv[:, 0])[0]
    bv = basis_matrix(s.knots[1], s.degrees[1], uv[:, 1])[0]
    h = np.einsum("ni,nj,ijd->nd", bu, bv, s.homogeneous())
    return h[:, :3] / h[:, 3:]


def _r(x):
    return repr(float(x))


def _write_all(s, tmp):
    """The surface in every format the readers take -> {format: path}."""
    n_u, n_v = s.shape
    w = s.weights
    pts, (ku, kv) = s.control_points, s.knots
    files = {}
    flat_u_fastest = pts.transpose(1, 0, 2).reshape(-1, 3)  # index v * n_u + u
    wf = w.T.ravel()
    text = (f"uOrder {s.degrees[0] + 1}\nvOrder {s.degrees[1] + 1}\nuDimension {n_u}\nvDimension {n_v}\n"
            f"uKnot [ {', '.join(map(_r, ku))} ]\nvKnot [ {', '.join(map(_r, kv))} ]\n"
            "controlPoint [\n" + ",\n".join(" ".join(map(_r, p)) for p in flat_u_fastest) + "\n]\n"
            f"weight [ {', '.join(map(_r, wf))} ]\n")
    files["nurbs-text"] = tmp / "s.nurbs"
    files["nurbs-text"].write_text(text)
    coefs = " ".join(" ".join(map(_r, p)) for p in flat_u_fastest)
    xml = ('<!-- a comment first -->\n<?xml version="1.0"?>\n<xml><Geometry type="TensorNurbs2" id="0">'
           '<Basis type="TensorNurbsBasis2"><Basis type="TensorBSplineBasis2">'
           + "".join(f'<Basis type="BSplineBasis" index="{a}"><KnotVector degree="{s.degrees[a]}">'
                     f'{" ".join(map(_r, k))}</KnotVector></Basis>' for a, k in enumerate((ku, kv)))
           + f'</Basis><weights>{" ".join(map(_r, wf))}</weights></Basis>'
           f'<coefs geoDim="3">{coefs}</coefs></Geometry></xml>')
    files["gismo-xml"] = tmp / "s.xml"
    files["gismo-xml"].write_text(xml)
    # IRIT: orders, rational points weight first and premultiplied, u fastest
    hp = s.homogeneous().transpose(1, 0, 2).reshape(-1, 4)
    body = "\n".join(f"    [{_r(p[3])} {_r(p[0])} {_r(p[1])} {_r(p[2])}]" for p in hp)
    itd = (f"[OBJECT SRF\n  [SURFACE BSPLINE {n_u} {n_v} {s.degrees[0] + 1} {s.degrees[1] + 1} P3\n"
           f"    [KV {' '.join(map(_r, ku))}]\n    [KV {' '.join(map(_r, kv))}]\n{body}\n  ]\n]\n")
    files["irit-itd"] = tmp / "s.itd"
    files["irit-itd"].write_text(itd)
    # geomdl: v fastest
    data = {"shape": {"type": "surface", "count": 1, "data": [{
        "degree_u": s.degrees[0], "degree_v": s.degrees[1], "knotvector_u": ku.tolist(), "knotvector_v": kv.tolist(),
        "size_u": n_u, "size_v": n_v, "rational": True, "dimension": 3,
        "control_points": {"points": pts.reshape(-1, 3).tolist(), "weights": w.ravel().tolist()}}]}}
    files["geomdl-json"] = tmp / "s.json"
    files["geomdl-json"].write_text(json.dumps(data))
    return files


def test_every_reader_reads_the_hand_made_surface(tmp_path):
    s = _small()
    uv = np.random.default_rng(0).uniform(0, 1, (50, 2))
    ref = _reference(s, uv)
    for fmt, path in _write_all(s, tmp_path).items():
        got, meta = load_surface_with_meta(path)
        assert meta["format"] == fmt
        assert np.allclose(got.evaluate(uv), ref, atol=1e-12), fmt
        assert np.allclose(got.derivatives(uv, 1)[:, 1, 0], s.derivatives(uv, 1)[:, 1, 0], atol=1e-10), fmt


def test_derivatives_match_differences_and_geomdl():
    s = _small()
    uv = np.random.default_rng(1).uniform(0.05, 0.95, (20, 2))
    d = s.derivatives(uv, 2)
    h = 1e-6
    for k, e in ((0, np.array([h, 0])), (1, np.array([0, h]))):
        fd = (s.evaluate(uv + e) - s.evaluate(uv - e)) / (2 * h)
        assert np.allclose(d[:, 1 - k, k], fd, atol=1e-6)
    fd = (s.derivatives(uv + [0, h], 1)[:, 1, 0] - s.derivatives(uv - [0, h], 1)[:, 1, 0]) / (2 * h)
    assert np.allclose(d[:, 1, 1], fd, atol=1e-5)
    geomdl = pytest.importorskip("geomdl")
    from geomdl import NURBS

    g = NURBS.Surface()
    g.degree_u, g.degree_v = s.degrees
    g.ctrlpts_size_u, g.ctrlpts_size_v = s.shape
    hp = s.homogeneous()
    g.ctrlptsw = hp.reshape(-1, 4).tolist()  # v fastest, weighted
    g.knotvector_u, g.knotvector_v = s.knots[0].tolist(), s.knots[1].tolist()
    for p, q in zip(uv[:5], d[:5], strict=True):
        skl = np.array(g.derivatives(float(p[0]), float(p[1]), order=2))
        assert np.allclose(skl[0, 0], q[0, 0], atol=1e-10)
        assert np.allclose(skl[1, 0], q[1, 0], atol=1e-8)
        assert np.allclose(skl[1, 1], q[1, 1], atol=1e-7)
        assert np.allclose(skl[0, 2], q[0, 2], atol=1e-7)
    assert geomdl is not None


@pytest.mark.parametrize("rational", [True, False])
def test_compiled_derivatives_match_the_numpy_sums(rational):
    """The compiled second-order kernel against the numpy reference, on knots, the domain's ends and beyond it
    (clamped), for every order the kernel serves."""
    s = _small(rational)
    rng = np.random.default_rng(7)
    uv = np.concatenate([rng.uniform(-0.1, 1.1, (400, 2)), [[0.4, 0.5], [0, 0], [1, 1], [0, 1]]])
    for order in (0, 1, 2):
        ref = s._numpy_sums(np.clip(uv, 0, 1), order)
        assert np.allclose(s._compiled_sums(uv, order), ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    assert s.derivatives(uv, 3).shape == (len(uv), 4, 4, 3)  # beyond the kernel: the numpy path


def test_compiled_distance_matches_the_numpy_newton():
    """shell.distance_to's compiled kernel takes the numpy loop's steps: the same distances, and they are true
    distances (no point of a dense sample is nearer)."""
    from volpuzzle.shell import _distance_numpy, distance_to

    s = _small()
    rng = np.random.default_rng(3)
    uv = rng.uniform(0.05, 0.95, (300, 2))
    x = s.evaluate(uv) + 0.3 * s.normals(uv) + rng.normal(0, 0.05, (300, 3))
    start = np.clip(uv + rng.normal(0, 0.03, uv.shape), 0, 1)
    d = distance_to(s, x, start)
    assert np.allclose(d, _distance_numpy(s, x, start), rtol=0, atol=1e-9)
    g = np.stack(np.meshgrid(np.linspace(0, 1, 200), np.linspace(0, 1, 200), indexing="ij"), -1).reshape(-1, 2)
    dense = s.evaluate(g)
    nearest = np.min(np.linalg.norm(x[:, None] - dense[None], axis=2), axis=1)
    assert np.all(d <= nearest + 1e-9) and np.all(d >= nearest - 0.02)


def test_duck_file_poles_and_seam():
    s = load_surface(DATA / "glscene_duck1.nurbs")
    assert s.degrees == (3, 3) and s.shape == (13, 14)
    (u0, u1), (v0, v1) = s.domain
    assert (u0, v0, u1, v1) == (-3.14159, -1.5708, 3.14159, 1.5708)
    u = np.linspace(u0, u1, 7)
    south = s.evaluate(np.stack([u, np.full(7, v0)], 1))
    north = s.evaluate(np.stack([u, np.full(7, v1)], 1))
    assert np.allclose(south, [1.49662, 0.0131926, -0.535702], atol=1e-12)  # the first row collapses
    assert np.allclose(north, north[0], atol=1e-12)
    seam = s.evaluate(np.array([[u0, 0.0], [u1, 0.0]]))
    assert np.allclose(seam[0], seam[1], atol=1e-12)  # each row closes on itself
    assert np.allclose(seam[0], [3.23694087, 0.0131926, 1.63632436], atol=1e-7)


def test_nurbs_file_as_a_volume_points_to_shell():
    from volpuzzle.io import load_model

    with pytest.raises(ModelError, match="model: {shell:"):
        load_model(DATA / "glscene_duck1.nurbs")


def _sphere_surface(r=40.0):
    from volpuzzle.models import sphere_shell

    vol = sphere_shell(outer_radius=r, inner_radius=r / 2)
    return Surface.from_volume_slab(vol, -1)


def test_sphere_shell_is_exact_and_its_volume_is_the_integral():
    r, t = 40.0, 5.0
    shell = make_shell(_sphere_surface(r), t, target=0.01)
    info = shell.info
    assert info["offset_max_error_mm"] < 1e-4 and info["method"].startswith("exact")
    assert info["closed_axes"] == ["v"] and sorted(info["poles"]) == ["u_max", "u_min"]
    exact = 4 / 3 * math.pi * (r ** 3 - (r - t) ** 3)
    assert volume_of(shell.volume) == pytest.approx(exact, rel=1e-9)


def test_freeform_shell_volume_within_the_offset_error():
    # an ellipsoid: its offset is not rational, so it is fitted
    s = _sphere_surface(1.0).transformed(np.diag([60.0, 40.0, 30.0]))
    t = 4.0
    shell = make_shell(s, t, target=0.01)
    err = shell.info["offset_max_error_mm"]
    assert 0 < err < 0.05
    # the volume between a closed surface and its inward offset (Steiner): t A - t^2 int H + t^3 int K / 3
    surf = shell.surface
    (u0, u1), (v0, v1) = surf.domain
    x, wu = np.polynomial.legendre.leggauss(60)
    uu = 0.5 * (u0 + u1) + 0.5 * (u1 - u0) * x
    vv = 0.5 * (v0 + v1) + 0.5 * (v1 - v0) * np.concatenate([x - 1, x + 1]) / 2
    wv = np.concatenate([wu, wu]) / 2
    uv = np.stack(np.meshgrid(uu, vv, indexing="ij"), -1).reshape(-1, 2)
    wt = (np.outer(wu, wv) * 0.25 * (u1 - u0) * (v1 - v0)).ravel()
    d = surf.derivatives(uv, 2)
    su, sv = d[:, 1, 0], d[:, 0, 1]
    n = np.cross(su, sv)
    da = np.linalg.norm(n, axis=1)
    n = n / da[:, None]
    E, F, G = (np.einsum("ni,ni->n", a, b) for a, b in ((su, su), (su, sv), (sv, sv)))
    L, M, N = (np.einsum("ni,ni->n", a, -n) for a in (d[:, 2, 0], d[:, 1, 1], d[:, 0, 2]))
    H = (E * N - 2 * F * M + G * L) / (2 * (E * G - F * F))
    K = (L * N - M * M) / (E * G - F * F)
    area, mean, gauss = (float(np.sum(q * da * wt)) for q in (np.ones_like(H), H, K))
    between = t * area - t ** 2 * mean + t ** 3 * gauss / 3
    # within the offset error times the area, plus the quadrature error of these integrals across knots
    assert abs(volume_of(shell.volume) - between) <= err * area + 1e-3 * between


@pytest.mark.slow  # the advice bisects the thickness over shell fits, and checks it on the full fit
def test_too_thick_shell_is_refused_with_the_place():
    s = _sphere_surface(1.0).transformed(np.diag([60.0, 40.0, 12.0]))
    radius, uv, xyz = tightest_inner_bend(s)
    assert radius < 5.0  # the rim of a flat ellipsoid bends tightly
    with pytest.raises(ModelError) as e:
        make_shell(s, 8.0, target=0.05)
    msg = str(e.value)
    assert msg.startswith("model.shell.thickness: a 8 mm shell folds")
    assert "xyz (" in msg and "expected at most" in msg


def test_shell_spec_key_is_checked(tmp_path):
    from volpuzzle.errors import SpecError
    from volpuzzle.spec import load_spec_text

    (tmp_path / "d.nurbs").write_text((DATA / "glscene_duck1.nurbs").read_text())
    spec = load_spec_text("name: d\nmodel: {shell: {surface: d.nurbs, thickness: 3}, size: 100}\ngrid: [1, 2, 1]\n",
                          tmp_path / "s.yaml")
    assert spec.model.shell.thickness == 3.0 and spec.model.size == 100
    with pytest.raises(SpecError, match=r"model.shell.thickness: .*got -1"):
        load_spec_text("name: d\nmodel: {shell: {surface: d.nurbs, thickness: -1}}\ngrid: [1, 2, 1]\n",
                       tmp_path / "s.yaml")


def test_duck_scaled_to_size_in_mm():
    s, scale = scale_to_mm(load_surface(DATA / "glscene_duck1.nurbs"), 1.0, 150.0)
    pts = s.evaluate_grid(np.linspace(*s.domain[0], 80), np.linspace(*s.domain[1], 80)).reshape(-1, 3)
    assert np.max(np.ptp(pts, axis=0)) == pytest.approx(150.0, rel=2e-3)
