"""Encoder -> ONNX, with a parity check against torch.

The graph takes ``x`` (batch, 25, channels) float32 in *tactile units* and normalises it inside
(``(x - mean) / std``, the training statistics as constants), then runs the bidirectional GRU
encoder and the nearest-code search: outputs ``z`` (batch, latent) float32 and ``code`` (batch,)
int64. The robot feeds :func:`edge.core.preprocess.model_input` straight in.

Exporter: the TorchScript exporter (``dynamo=False``, opset 17) emits the native ONNX ``GRU``
op and a symbolic batch dimension. (The dynamo exporter unrolled the GRU into a per-step
graph and mishandled a dynamic batch in a trial.) The GRU's initial state is built from
``Shape(x)``, so every batch size works even though torch warns about GRU batch sizes; the
parity check runs batch 1 and batch 7 to prove it.
"""

from __future__ import annotations

import io
import json
import logging
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import torch

from edge.core.atomic import atomic_write_bytes
from edge.core.errors import ModelError
from edge.core.model import INPUT_NAME, OUTPUT_NAMES, OnnxEncoder, nearest_code
from train.learn.data import Normaliser
from train.learn.model import ExportEncoder, TactileAutoencoder

log = logging.getLogger(__name__)

OPSET = 17
# onnxruntime and torch run the same float32 GRU with different kernels; measured
# differences are ~1e-7, so anything above this bound is a real export bug.
PARITY_BOUND = 1e-5
# The codebook travels inside the ONNX file (metadata), so the database can quantise
# queries with exactly the codes the graph uses.
CODEBOOK_KEY = "vtzero.codebook"


def export_onnx(model: TactileAutoencoder, norm: Normaliser, path: str | Path) -> bytes:
    """Write the encoder graph to ``path`` atomically; returns the bytes written."""
    wrapper = ExportEncoder(model, norm.mean, norm.std).eval()
    cfg = model.cfg
    example = torch.zeros(2, cfg.steps, cfg.channels)
    buf = io.BytesIO()
    with warnings.catch_warnings():
        # The legacy exporter is deprecated but is the one that keeps the GRU a single op;
        # its GRU batch-size warning is answered by the batch 1 / batch 7 parity check.
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.filterwarnings("ignore", message=".*batch_size other than 1.*")
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        torch.onnx.export(
            wrapper, (example,), buf, dynamo=False, opset_version=OPSET,
            input_names=[INPUT_NAME], output_names=list(OUTPUT_NAMES),
            dynamic_axes={INPUT_NAME: {0: "batch"}, "z": {0: "batch"}, "code": {0: "batch"}},
            do_constant_folding=True)
    proto = onnx.load_from_string(buf.getvalue())
    onnx.checker.check_model(proto)
    ops = {n.op_type for n in proto.graph.node}
    if "GRU" not in ops:
        raise ModelError(f"export produced no native GRU op (ops: {sorted(ops)})")
    proto.doc_string = ("vtzero tactile encoder: x (batch, steps, channels) float32 in tactile "
                        "units (raw - tare) / 65536, normalised inside; z (batch, latent) "
                        "float32, code (batch,) int64 nearest codebook index")
    assert model.quantiser is not None
    codebook = model.quantiser.codebook.detach().numpy().astype(np.float32)
    for key, value in (("vtzero.input_units", "(raw - tare) / 65536"),
                       ("vtzero.normalisation", "inside graph: (x - mean) / std"),
                       ("vtzero.latent", str(cfg.latent)),
                       # float32 -> float -> JSON round-trips exactly.
                       (CODEBOOK_KEY, json.dumps(codebook.tolist()))):
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    data = proto.SerializeToString()
    atomic_write_bytes(path, data)
    return data


@dataclass(frozen=True)
class Parity:
    max_abs_z: float
    code_mismatches: int
    cases: int

    def to_dict(self) -> dict[str, float | int]:
        return {"max_abs_diff_z": self.max_abs_z, "code_mismatches": self.code_mismatches,
                "inputs_compared": self.cases}


@torch.no_grad()
def parity(model: TactileAutoencoder, norm: Normaliser, onnx_model: bytes | str | Path,
           real: np.ndarray | None = None, seed: int = 0) -> Parity:
    """onnxruntime vs torch on random inputs (batch 1 and 7) and on ``real`` inputs.

    Random inputs are drawn at the scale of the training data (per-channel mean and std);
    real ones are recognition-time inputs in tactile units.
    """
    wrapper = ExportEncoder(model, norm.mean, norm.std).eval()
    session = OnnxEncoder(onnx_model)
    book = codebook_of(onnx_model)
    rng = np.random.default_rng(seed)
    batches = [(norm.mean + norm.std * rng.standard_normal((b, session.steps,
                                                            session.channels))
                ).astype(np.float32) for b in (1, 7)]
    if real is not None and len(real):
        real = np.asarray(real, dtype=np.float32)
        batches += [real[:1], real[:7], real]
    worst, mismatches, cases = 0.0, 0, 0
    for x in batches:
        z_ort, code_ort = session(x)
        z_t, code_t = wrapper(torch.from_numpy(x))
        worst = max(worst, float(np.abs(z_ort - z_t.numpy()).max()))
        mismatches += int((code_ort != code_t.numpy()).sum())
        # The metadata codebook must reproduce the graph's own choice of code.
        mismatches += int((nearest_code(z_ort, book) != code_ort).sum())
        cases += len(x)
    return Parity(worst, mismatches, cases)


def check_parity(result: Parity, bound: float = PARITY_BOUND) -> None:
    if not result.max_abs_z < bound:
        raise ModelError(f"ONNX parity failed: max |z_onnx - z_torch| = {result.max_abs_z:.3g} "
                         f">= {bound:g}")
    if result.code_mismatches:
        log.warning("ONNX and torch chose different codes for %d of %d inputs (near-ties)",
                    result.code_mismatches, result.cases)


def codebook_of(onnx_model: bytes | str | Path) -> np.ndarray:
    """The codebook (K, D) float32 stored in an exported encoder's metadata."""
    proto = onnx.load_from_string(onnx_model) if isinstance(onnx_model, bytes) \
        else onnx.load(str(onnx_model))
    for prop in proto.metadata_props:
        if prop.key == CODEBOOK_KEY:
            book = np.asarray(json.loads(prop.value), dtype=np.float32)
            if book.ndim == 2:
                return book
    raise ModelError("encoder has no codebook in its metadata: re-export it with vt-train")
