"""What other masters read in modelDescription.xml (issue 8.10): dependencies, ranges, units,
generator and date, self-contained descriptions."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import pytest

import fmus
from hil.fmu.spec import generate_model_description, guid, load_spec


def description(name: str) -> ET.Element:
    spec = load_spec(fmus.source_root() / name)
    return ET.fromstring(generate_model_description(spec, guid(spec, "digest")))


def variables(root: ET.Element) -> dict[str, tuple[int, ET.Element]]:
    return {v.get("name"): (i + 1, v) for i, v in enumerate(root.iter("ScalarVariable"))}


@pytest.mark.parametrize("name", ["DriveCylinder", "FeaSegment"])
def test_outputs_declare_no_direct_feedthrough(name: str) -> None:
    root = description(name)
    unknowns = root.find("ModelStructure/Outputs").findall("Unknown")
    assert unknowns and all(u.get("dependencies") == "" for u in unknowns)


def test_initial_unknowns_depend_only_on_what_they_follow() -> None:
    seg = description("FeaSegment")
    index = {name: i for name, (i, _) in variables(seg).items()}
    initial = {
        int(u.get("index")): set(map(int, u.get("dependencies").split()))
        for u in seg.find("ModelStructure/InitialUnknowns")
    }
    assert index["x_piston"] in initial[index["p_a"]]
    assert index["x_piston"] not in initial[index["theta"]]
    assert index["tau_ext"] not in initial[index["p_a"]]
    cyl = description("DriveCylinder")
    cindex = {name: i for name, (i, _) in variables(cyl).items()}
    for u in cyl.find("ModelStructure/InitialUnknowns"):
        deps = set(map(int, u.get("dependencies").split()))
        assert not deps & {cindex[n] for n in ("x_ref", "enable", "p_a", "p_b")}


def test_units_ranges_generator_and_descriptions() -> None:
    seg, cyl = description("FeaSegment"), description("DriveCylinder")
    g_a = variables(seg)["G_a"][1].find("Real")
    assert g_a.get("unit") == "m3/rad"
    units = {u.get("name"): u.find("BaseUnit").attrib for u in seg.iter("Unit")}
    assert units["m3/rad"] == {"m": "3", "rad": "-1"}
    assert variables(seg)["x_piston"][1].find("Real").get("min") == "0.0"
    for side in ("p_a", "p_b"):
        assert float(variables(cyl)[side][1].find("Real").get("min")) == -101325.0
    for root in (seg, cyl):
        assert root.get("generationTool").startswith("softhil ")
        texts = [root.get("description")] + [
            v.get("description") for v in root.iter("ScalarVariable")
        ]
        assert not any(".md" in text or "section" in text for text in texts)


def test_generation_date_comes_from_the_sources_not_the_clock(monkeypatch) -> None:
    first = description("FeaSegment").get("generationDateAndTime")
    assert first == description("FeaSegment").get("generationDateAndTime")
    assert first.endswith("Z") and len(first) == len("2020-01-01T00:00:00Z")
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    assert description("FeaSegment").get("generationDateAndTime") == "2023-11-14T22:13:20Z"
