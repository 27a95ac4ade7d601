"""The shipped models/ as the paper's method needs it: descriptions that name objects, the
paper's prompt, a database of every offset of every press, the experiments' results marked as
the simulated VLM's, and a README whose figures come from them."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import pytest

from edge.core.descriptions import check_description, tactile_words
from edge.core.errors import DescriptionError, ModelError
from edge.core.model import EMULATED_ORIGIN, Origin, load_model, model_ref
from edge.sim import catalogue

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"


@pytest.fixture(scope="module")
def model():
    return load_model(MODELS)


def test_shipped_descriptions_name_objects_and_never_say_how_they_feel(model):
    index = json.loads((MODELS / "database.json").read_text())
    for c in index["classes"]:
        assert tactile_words(c["description"]) == [], c
        check_description(c["description"], c["label"])
        # A name, made unambiguous: not the bare label, not a sentence about it.
        assert len(c["description"].split()) <= 12, c
    # The recorder writes the catalogue's descriptions: the same rule holds there.
    for obj in catalogue.REFERENCE:
        check_description(obj.description, obj.name)
    assert model.database.description("otedama").startswith("otedama (")


@pytest.mark.parametrize("text", ["a cube of hard wood", "soft tofu", "springy rubber",
                                  "smooth glass", "firmly packed rice", "it gives a little"])
def test_tactile_words_are_caught(text):
    with pytest.raises(DescriptionError, match="says how the object feels"):
        check_description(text)


def test_database_holds_fifty_references_per_class(model):
    db = model.database
    assert len(db) == 1600 and len(db.classes) == 32 and db.offsets == [0, 1, 2, 3, 4]
    index = json.loads((MODELS / "database.json").read_text())
    assert all(c["presses"] == 10 and c["references"] == 50 for c in index["classes"])


def test_manifest_records_the_prompt_hashes(model):
    prompts = model.manifest["prompts"]
    for mode in ("vision_tactile", "vision_only", "tactile_only"):
        data = (MODELS / "prompts" / f"{mode}.txt").read_bytes()
        assert prompts[mode]["sha256"] == hashlib.sha256(data).hexdigest()
        assert prompts[mode]["sha256"] == model.manifest["files"][f"prompts/{mode}.txt"][
            "sha256"]
    assert prompts["vision_tactile"]["slots"] == ["test_time_classes", "topk_refs"]
    assert model.manifest["training"]["vq"]["config"]["model"]["decoder"] == "teacher"


def test_shipped_experiments_are_titled_as_the_simulated_vlm(model):
    table = (MODELS / "eval" / "table1" / "table1.md").read_text()
    assert table.startswith("# Table I (simulated VLM)") and "not a real model" in table
    saved = json.loads((MODELS / "eval" / "table1" / "table1.json").read_text())
    assert [m["model"] for m in saved["models"]] == ["simulated-vlm",
                                                     "simulated-vlm-vision-led"]
    # Asked with the shipped prompts and against the shipped database.
    assert saved["models"][0]["prompts"]["vision_tactile"]["sha256"] == \
        model.manifest["prompts"]["vision_tactile"]["sha256"]
    assert saved["tactile_model"]["database"]["references"] == len(model.database)
    fig = (MODELS / "eval" / "fig6" / "fig6.md").read_text()
    assert fig.startswith("# Fig. 6") and "(simulated VLM)" in fig
    sizes = [row["size"] for row in json.loads(
        (MODELS / "eval" / "fig6" / "fig6.json").read_text())["sizes"]]
    assert sizes == [0, 6, 13, 20, 27]
    for png in ("table1/confusion_simulated-vlm_foodreplica.png", "fig6/fig6.png"):
        assert (MODELS / "eval" / png).read_bytes()[:4] == b"\x89PNG"


def test_readme_takes_its_figures_from_the_generated_evaluation(model):
    readme = (ROOT / "README.md").read_text()
    for link in ("models/eval/eval.md", "models/eval/table1/table1.md",
                 "models/eval/fig6/fig6.md"):
        assert f"]({link})" in readme and (ROOT / link).exists()
    # No hand-copied results: AUCs, 1-NN accuracies, accuracies in percent of the tables.
    section = readme[readme.index("## Training and the shipped model"):
                     readme.index("## The simulated robot")]
    assert not re.search(r"AUC \d|1-NN \d|\d+(\.\d+)? ?%|~\d+ s", section), section
    # The example touch sentence is made of real descriptions from the shipped database.
    example = re.search(r'\("similar to (.+?)"\)', readme.replace("\n", " "))
    assert example, "the README's example sentence"
    descriptions = {c.description for c in model.database.classes}
    items = re.split(r", (?![^()]*\))", " ".join(example.group(1).split()))
    assert len(items) == 3 and all(item in descriptions for item in items), items


def test_manifest_says_the_references_were_pressed_by_the_emulated_robot(model, tmp_path):
    assert model.origin.kind == "emulated" and "emulated robot" in model.origin.recorder
    manifest = json.loads((MODELS / "manifest.json").read_text())
    # A release made before the key reads as emulated; a malformed one is refused by name.
    del manifest["origin"]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    assert model_ref(tmp_path).origin == EMULATED_ORIGIN
    manifest["origin"] = {"kind": "robot", "recorder": "lab", "robot": "arm-3",
                          "sensor": {"model": "XR1944", "serials": ["A1", "B2"]}}
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    origin = model_ref(tmp_path).origin
    assert origin == Origin("robot", "lab", "arm-3", "XR1944", ("A1", "B2"))
    assert Origin.from_json(origin.to_json()) == origin
    manifest["origin"] = {"kind": "real"}
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ModelError, match=r"manifest\.json: origin kind must be"):
        model_ref(tmp_path)
