import json
import subprocess
import sys

import numpy as np
import pytest

from edge.core.errors import ModelError
from edge.core.model import load_model
from train.learn.data import load_presses


def test_load_encode_topk_describe(released, cube_dir):
    model = load_model(released)
    x = load_presses(cube_dir).inputs(0)
    z, code = model.encode(x[0])
    assert z.shape == (16,) and z.dtype == np.float32 and isinstance(code, int)
    zb, codes = model.encode(x)
    assert zb.shape == (len(x), 16) and codes.shape == (len(x),)
    np.testing.assert_allclose(zb[0], z, atol=1e-6)
    top = model.topk(z, k=3)
    assert len(top) == 3 and len({lab for lab, _ in top}) == 3
    assert [d for _, d in top] == sorted(d for _, d in top)
    sentence = model.describe([lab for lab, _ in top])
    assert sentence.count(", ") >= 2 and all(lab in model.labels for lab, _ in top)


def test_encode_refuses_bad_input(released):
    model = load_model(released)
    with pytest.raises(ModelError, match=r"\(25, 96\)"):
        model.encode(np.zeros((24, 96), dtype=np.float32))
    with pytest.raises(ModelError, match="NaN"):
        model.encode(np.full((25, 96), np.nan, dtype=np.float32))


@pytest.mark.parametrize("victim", ["encoder.onnx", "database.npz", "database.json"])
def test_hash_mismatch_is_refused_naming_the_file(model_copy, victim):
    model_dir = model_copy
    path = model_dir / victim
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(ModelError, match=rf"{victim}: sha256 .* does not match the manifest"):
        load_model(model_dir)


def test_missing_file_and_missing_manifest_are_refused(model_copy):
    model_dir = model_copy
    (model_dir / "database.npz").unlink()
    with pytest.raises(ModelError, match=r"database\.npz: missing"):
        load_model(model_dir)
    (model_dir / "manifest.json").unlink()
    with pytest.raises(ModelError, match=r"manifest\.json: missing"):
        load_model(model_dir)


def test_prompts_are_hashed_and_checked(model_copy):
    from train.ship.manifest import write_manifest

    model_dir = model_copy
    (model_dir / "prompts").mkdir()
    (model_dir / "prompts" / "vision_tactile.txt").write_text("${topk_refs}\n")
    write_manifest(model_dir)
    files = json.loads((model_dir / "manifest.json").read_text())["files"]
    assert "prompts/vision_tactile.txt" in files
    load_model(model_dir)
    (model_dir / "prompts" / "vision_tactile.txt").write_text("changed\n")
    with pytest.raises(ModelError, match=r"vision_tactile\.txt: sha256"):
        load_model(model_dir)


def test_manifest_names_cannot_leave_the_directory(model_copy):
    model_dir = model_copy
    manifest = json.loads((model_dir / "manifest.json").read_text())
    manifest["files"]["../secret"] = {"sha256": "0" * 64}
    (model_dir / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ModelError, match="leaves the directory"):
        load_model(model_dir)


def test_edge_model_imports_no_torch(released):
    code = f"""
import importlib.abc, sys
class NoTorch(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ModuleNotFoundError("torch blocked")
sys.meta_path.insert(0, NoTorch())
import numpy as np
from edge.core.model import load_model
m = load_model({str(released)!r})
z, c = m.encode(np.zeros((25, 96), np.float32))
print(m.describe(l for l, _ in m.topk(z)))
assert "torch" not in sys.modules
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
