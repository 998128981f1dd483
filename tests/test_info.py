"""`volpuzzle info` data: the SPEC section 3 keys, values against the reference table, and the fold report."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from volpuzzle.info import format_info, model_info
from volpuzzle.io import load_model_with_meta
from volpuzzle.spline.volume import Volume

DATA = Path(__file__).parent / "data" / "volumes"
REFERENCE = {Path(r["file_here"]).name: r
             for r in csv.DictReader(open(DATA / "REFERENCE_VALUES.tsv"), delimiter="\t")}
SPEC_KEYS = {"degrees", "control_points", "domain", "periodic", "bbox", "volume", "handedness", "jacobian_min",
             "jacobian_max"}


def info_of(name, patch=0):
    vol, meta = load_model_with_meta(DATA / name, patch=patch)
    return model_info(vol, DATA / name, patch, meta)


@pytest.mark.parametrize("name", ["gismo_twisted_pipe.xml", "gismo_cylinder.xml", "gismo_bent_pipe.xml"])
def test_info_has_the_spec_keys_and_is_json(name):
    d = info_of(name)
    assert SPEC_KEYS <= set(d)
    back = json.loads(json.dumps(d))
    assert back["control_points"] == list(load_model_with_meta(DATA / name)[0].shape)
    assert len(back["domain"]) == 3 and len(back["bbox"]) == 2 and len(back["bbox"][0]) == 3
    assert back["volume"] > 0 and back["handedness"] in ("right", "left")
    assert back["jacobian_min"] <= back["jacobian_max"]


@pytest.mark.parametrize("name", ["gismo_twisted_pipe.xml", "gismo_cylinder.xml", "gismo_spring.xml",
                                  "gismo_bent_pipe.xml"])
def test_info_matches_reference(name):
    d, ref = info_of(name), REFERENCE[name]
    pos, neg = (int(x) for x in ref["signs(+/-)"].split("/"))
    assert d["handedness"] == ("right" if pos else "left")
    vol_ref = float(ref["sum_abs_volume"])
    assert abs(d["volume"] - vol_ref) <= 1.5e-6 * vol_ref + 5e-7
    # bbox: the exact box contains the reference's sampled box and is close to it
    lo, hi = np.array(d["bbox"])
    rlo, rhi = np.array(json.loads(ref["geom_bbox_min"])), np.array(json.loads(ref["geom_bbox_max"]))
    tol = 1e-3 * np.linalg.norm(rhi - rlo)
    assert np.all(lo <= rlo + tol) and np.all(hi >= rhi - tol)
    assert np.all(np.abs(lo - rlo) <= 0.02 * np.linalg.norm(rhi - rlo))
    # coefficient bounds enclose the sampled Jacobian, and have one sign for these valid models
    smin, smax = d["jacobian_sampled"]
    assert d["jacobian_min"] <= smin + 1e-9 * abs(smin) and d["jacobian_max"] >= smax - 1e-9 * abs(smax)
    assert "fold" not in d


def test_info_periodic_axes():
    assert info_of("gismo_cylinder.xml")["periodic"] == ["u"]
    assert info_of("gismo_spring.xml")["periodic"] == []


def test_info_reports_a_fold_with_its_place():
    # The middle u-slab of control points pushed past the last one: det J < 0 near u = 1.
    cps = np.stack(np.meshgrid([0.0, 1.0, 2.0], [0.0, 1.0], [0.0, 1.0], indexing="ij"), -1)
    cps[1, :, :, 0] = 2.5
    vol = Volume((2, 1, 1), [[0, 0, 0, 1, 1, 1], [0, 0, 1, 1], [0, 0, 1, 1]], cps)
    d = model_info(vol)
    assert "fold" in d and d["jacobian_min"] < 0 < d["jacobian_max"]
    u = d["fold"]["uvw"][0]
    assert u > 0.8 and "changes sign" in d["fold"]["message"]
    assert "FOLD" in format_info(d)


def test_format_info_is_short_and_aligned():
    text = format_info(info_of("gismo_water_passage_3p.xml", patch=1))
    lines = text.splitlines()
    assert 8 <= len(lines) <= 14 and "patch 1 of 3" in lines[0]
    starts = {len(line) - len(line.split("  ", 1)[1].lstrip()) for line in lines if "  " in line}
    assert len(starts) == 1  # values start in one column
