"""Loading the live panel's LPV model from a report's results.json (Qt-free)."""

from __future__ import annotations

import json

import pytest

from steerlab.analysis.lpv import PhysicalLPV
from steerlab.analysis.lpv_results import LPVLoadError, load_lpv_model, lpv_from_document

P = {"I_i": 0.02, "b_i": 1.5, "k_i": 25.0, "b_c": 4.0, "k_c": 500.0}


def _pt(cond, mu, k_i, **kw):
    return {"condition": cond, "mu_N": mu, "parameters": {**P, "k_i": k_i}, **kw}


def test_results_json_shape_and_rt_left_out(tmp_path):
    pts = [
        _pt("RT", 70.0, 8.0, included=False),
        _pt("BT18", 80.0, 18.0, included=True),
        _pt("BT8", 120.0, 30.0, included=True),
        _pt("PT", 200.0, 60.0, included=True),
    ]
    doc = {"lpv": {"order": 2, "error": None, "operating_points": pts}}
    (tmp_path / "results.json").write_text(json.dumps(doc))
    m = load_lpv_model(tmp_path / "results.json")
    assert m.conditions == ("BT18", "BT8", "PT") and m.excluded == ("RT",) and m.order == 2
    ref = PhysicalLPV.fit([(p["condition"], p["mu_N"], p["parameters"])
                           for p in doc["lpv"]["operating_points"][1:]], order=2)  # fmt: skip
    assert m.model.parameters(100.0) == pytest.approx(ref.parameters(100.0))
    assert "RT" in m.describe()


def test_bare_list_values_as_objects_and_order_lowered():
    pts = [_pt("A", 50.0, 10.0), _pt("B", 90.0, 20.0)]
    pts[0]["parameters"]["k_i"] = {"value": 10.0, "sem": 1.0}
    m = lpv_from_document(pts)
    assert m.order == 1  # two points cannot carry a quadratic
    assert m.model.parameters(70.0)["k_i"] == pytest.approx(15.0)


@pytest.mark.parametrize(
    "doc, match",
    [
        ({"lpv": None}, "no LPV section"),
        ({"lpv": {"operating_points": [], "error": "too few conditions"}}, "too few conditions"),
        ({"something": 1}, "no lpv.operating_points"),
        ([{"condition": "A", "mu_N": 1.0, "parameters": {"k_i": 1.0}}], "miss"),
        ([_pt("A", float("nan"), 1.0), _pt("B", 2.0, 1.0)], "finite"),
    ],
)
def test_unusable_documents_say_why(doc, match):
    with pytest.raises(LPVLoadError, match=match):
        lpv_from_document(doc)


def test_unreadable_file(tmp_path):
    with pytest.raises(LPVLoadError, match="cannot read"):
        load_lpv_model(tmp_path / "missing.json")
    (tmp_path / "x.json").write_text("{not json")
    with pytest.raises(LPVLoadError, match="not a JSON file"):
        load_lpv_model(tmp_path / "x.json")
