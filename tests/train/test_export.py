import numpy as np
import onnx
import torch

from edge.core.model import OnnxEncoder
from train.learn.model import ExportEncoder
from train.ship.export import PARITY_BOUND, codebook_of, export_onnx, parity


def test_onnx_matches_torch_batch_1_and_7_random_and_real(trained, data, cube_dir, tmp_path):
    from train.learn.data import load_presses

    path = tmp_path / "encoder.onnx"
    blob = export_onnx(trained.model, data.norm, path)
    assert path.read_bytes() == blob
    real = np.concatenate([data.presses.inputs(0), load_presses(cube_dir).inputs(0)])
    result = parity(trained.model, data.norm, blob, real)
    print(f"ONNX parity: max |z_onnx - z_torch| = {result.max_abs_z:.3g} "
          f"over {result.cases} inputs")
    assert result.max_abs_z < PARITY_BOUND
    assert result.code_mismatches == 0
    # Explicit batch 1 and 7 through the session, against torch.
    session = OnnxEncoder(blob)
    wrapper = ExportEncoder(trained.model, data.norm.mean, data.norm.std).eval()
    for batch in (1, 7):
        x = real[:batch]
        z, code = session(x)
        zt, ct = wrapper(torch.from_numpy(x))
        assert z.shape == (batch, trained.config.model.latent) and code.shape == (batch,)
        assert np.abs(z - zt.detach().numpy()).max() < PARITY_BOUND
        np.testing.assert_array_equal(code, ct.numpy())


def test_graph_uses_the_native_gru_and_a_symbolic_batch(trained, data, tmp_path):
    blob = export_onnx(trained.model, data.norm, tmp_path / "e.onnx")
    proto = onnx.load_from_string(blob)
    ops = [n.op_type for n in proto.graph.node]
    assert ops.count("GRU") == 2 and "Loop" not in ops and "Scan" not in ops
    dim0 = proto.graph.input[0].type.tensor_type.shape.dim[0]
    assert dim0.dim_param == "batch"
    np.testing.assert_array_equal(
        codebook_of(blob), trained.model.quantiser.codebook.detach().numpy())


def test_export_is_byte_identical_for_the_same_weights(trained, data, tmp_path):
    a = export_onnx(trained.model, data.norm, tmp_path / "a.onnx")
    b = export_onnx(trained.model, data.norm, tmp_path / "b.onnx")
    assert a == b
