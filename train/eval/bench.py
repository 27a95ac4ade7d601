"""``vt-train bench``: the bench's figures that need torch, added to ``vt-edge bench``'s.

Phases:

1. **encode_torch**: the shipped encoder in torch eager (its weights read back from
   ``encoder.onnx``, parity with onnxruntime checked) against onnxruntime with the robot's
   session options, on the same inputs, in blocks alternating between the two so that both
   see the same host; the speed-up is the ratio of those two timings.
2. **train**: the shipped encoder's training configuration on a freshly recorded simulated
   reference set.

``vt-train bench --merge-into bench/results.json`` adds these figures to the results file
that ``vt-edge bench`` wrote (and renders its ``results.md`` again); ``--out DIR`` starts a
file of its own. One format for both: :mod:`edge.bench.results`. ``make bench`` runs
``vt-edge bench`` then this.
"""

from __future__ import annotations

import json
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from edge.bench.figures import figure, ratio_figure, target, timed_in_blocks
from edge.bench.results import PhaseResult, Results, progress, version
from edge.core.model import load_model, read_manifest, synthetic_inputs

MODELS = Path(__file__).resolve().parents[2] / "models"
PHASES = ("encode_torch", "train")
# Every figure this side writes, in table order.
FIGURES = ("encode_ms_torch", "encode_speedup_vs_torch", "train_s")


@dataclass(frozen=True)
class Settings:
    quick: bool
    encode_n: int  # timed single-sequence encodes, each runtime
    train_presses: int  # recorded reference presses per class
    train_max_epochs: int | None  # None: the shipped configuration's


FULL = Settings(quick=False, encode_n=2000, train_presses=10, train_max_epochs=None)
QUICK = replace(FULL, quick=True, encode_n=300, train_presses=2, train_max_epochs=3)

# Why a target is missed on this kind of host, and what would close it.
WHY: dict[str, str] = {
    "encode_speedup_vs_torch": (
        "The ratio moves with onnxruntime's time on a busy host (torch's ~1-2 ms per call "
        "hides the noise better); 11.5-12.8x was measured on a calmer moment with the same "
        "block method. To close it: a quiet core."),
}


def torch_encoder_from_onnx(path: Path, manifest: dict[str, Any]):
    """The shipped encoder as a torch module, weights read back from ``encoder.onnx``.

    ONNX GRU gates are ordered (z, r, h) and torch's (r, z, n); biases are [Wb | Rb]. The
    caller checks parity with onnxruntime before trusting it.
    """
    import onnx
    import torch
    from onnx import numpy_helper

    from train.learn.model import ExportEncoder, ModelConfig, TactileAutoencoder

    proto = onnx.load(str(path))
    init = {t.name: numpy_helper.to_array(t).copy() for t in proto.graph.initializer}
    cfg = ModelConfig.from_dict(manifest["training"]["vq"]["config"]["model"])
    model = TactileAutoencoder(cfg).eval()
    h = cfg.hidden

    def reorder(m: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.concatenate([m[h:2 * h], m[:h], m[2 * h:]]))

    grus = [n for n in proto.graph.node if n.op_type == "GRU"]
    if len(grus) != cfg.layers:
        raise ValueError(f"{len(grus)} GRU nodes in {path}, the model has {cfg.layers} layers")
    gru = model.encoder.gru
    with torch.no_grad():
        for layer, node in enumerate(grus):
            w, r, b = (init[name] for name in node.input[1:4])
            for d, suffix in enumerate(("", "_reverse")):
                getattr(gru, f"weight_ih_l{layer}{suffix}").copy_(reorder(w[d]))
                getattr(gru, f"weight_hh_l{layer}{suffix}").copy_(reorder(r[d]))
                getattr(gru, f"bias_ih_l{layer}{suffix}").copy_(reorder(b[d][:3 * h]))
                getattr(gru, f"bias_hh_l{layer}{suffix}").copy_(reorder(b[d][3 * h:]))
        model.encoder.head.weight.copy_(torch.from_numpy(init["encoder.head.weight"]))
        model.encoder.head.bias.copy_(torch.from_numpy(init["encoder.head.bias"]))
        meta = {p.key: p.value for p in proto.metadata_props}
        book = np.asarray(json.loads(meta["vtzero.codebook"]), dtype=np.float32)
        assert model.quantiser is not None
        model.quantiser.codebook.copy_(torch.from_numpy(book))
    return ExportEncoder(model, init["mean"], init["std"]).eval()


def encode_torch_phase(s: Settings, models: Path) -> PhaseResult:
    """torch eager against onnxruntime (edge.core.model) on the same weights and inputs."""
    if version("torch") is None:
        return PhaseResult({}, ["torch is not installed: no torch eager comparison"])
    import torch

    notes: list[str] = []
    model = load_model(models)
    xs = synthetic_inputs(model.manifest)
    torch.set_num_threads(1)
    wrapper = torch_encoder_from_onnx(models / "encoder.onnx", model.manifest)

    def torch_encode(x: np.ndarray) -> tuple[np.ndarray, int]:
        with torch.inference_mode():
            z, code = wrapper(torch.from_numpy(x[None]))
            return z.numpy()[0], int(code[0])

    worst = max(float(np.abs(torch_encode(x)[0] - model.encode(x)[0]).max()) for x in xs)
    progress(f"encoder: {s.encode_n} single-sequence encodes each: onnxruntime (1 thread, "
             f"the robot's options), torch {torch.__version__} eager (1 thread, same weights "
             f"and inputs, parity max |dz| {worst:.2g})")
    times = timed_in_blocks({"ort": model.encode, "torch": torch_encode}, xs, s.encode_n)
    ort = figure(times["ort"], "ms")
    figs = {"encode_ms_torch": figure(
        times["torch"], "ms", None, parity_max_abs_dz=worst,
        what="the same encoder in torch eager (weights read back from encoder.onnx), "
             "1 thread, inference_mode, same inputs, in blocks alternating with onnxruntime's")}
    figs["encode_speedup_vs_torch"] = ratio_figure(
        figs["encode_ms_torch"], ort, target(("p50", ">=", 10.0)),
        onnxruntime_ms={k: ort[k] for k in ("p50", "p99", "max", "n")},
        what="torch eager time / onnxruntime time (statistic by statistic), both timed in "
             "this phase's alternating blocks (onnxruntime_ms: its timing here)")
    if not worst < 1e-4:
        notes.append(f"torch reconstruction differs from onnxruntime (max |dz| {worst}): "
                     "the torch timing is of a different function")
    return PhaseResult(figs, notes)


def train_phase(s: Settings, tmp: Path, models: Path) -> PhaseResult:
    """The shipped encoder's training configuration on freshly recorded presses."""
    if version("torch") is None:
        return PhaseResult({}, ["torch is not installed: no training figure"])
    from edge.lab.record import record_dataset
    from train.learn.data import training_data
    from train.learn.trainer import Progress, TrainConfig, train

    manifest = read_manifest(models)
    shipped = manifest["training"]["vq"]
    config = TrainConfig.from_dict(shipped["config"])
    if s.train_max_epochs is not None:
        config = replace(config, max_epochs=s.train_max_epochs)
    rec_dir = tmp / "recordings"
    progress(f"training: recording {s.train_presses} simulated presses per reference class")
    t0 = time.perf_counter()
    record_dataset("reference", s.train_presses, rec_dir, seed=0)
    record_s = time.perf_counter() - t0
    data = training_data(rec_dir)
    progress(f"training: recorded in {record_s:.1f} s; training the VQ encoder "
             f"(shipped config, max {config.max_epochs} epochs, patience {config.patience}, "
             f"{config.threads} thread(s))")
    result = train(data, config, None, Progress())
    epochs_note = ("shipped configuration" if s.train_max_epochs is None
                   else f"QUICK: capped at {s.train_max_epochs} epochs, not the shipped run")
    fig = figure([result.seconds], "s", None, epochs=result.epochs,
                 best_epoch=result.best_epoch, stopped=result.stopped,
                 train_samples=len(data.train), record_s=record_s,
                 shipped_epochs=shipped["result"]["epochs"],
                 shipped_train_s=manifest.get("timings", {}).get("train_vq_s"),
                 what=f"train.learn.trainer.train of the VQ-VAE on {s.train_presses} fresh "
                      f"simulated presses per reference class ({epochs_note})")
    return PhaseResult({"train_s": fig})


def bench(s: Settings, *, merge_into: Path | None = None, out: Path | None = None,
          models: Path = MODELS, phases: tuple[str, ...] = PHASES) -> int:
    """Run the phases; add them to ``merge_into`` (a results.json of ``vt-edge bench``), or
    write a new results file in ``out``."""
    command = "vt-train bench" + (" --quick" if s.quick else "")
    if merge_into is not None:
        results = Results.load(merge_into)
        if bool(results.run.get("quick")) != s.quick:
            kind = "a quick" if results.run.get("quick") else "a full"
            raise ValueError(f"{merge_into} holds {kind} run: merge a run of the same kind "
                             f"({'with' if results.run.get('quick') else 'without'} --quick)")
        taken = [p for p in phases if p in results.run["phases"]]
        if taken:
            raise ValueError(f"{merge_into} already holds the phases {', '.join(taken)}: run "
                             "vt-edge bench again for a fresh file")
        results.add_command(f"{command} --merge-into {merge_into}", "train_settings",
                            asdict(s))
        out = merge_into.parent
    else:
        if out is None:
            raise ValueError("give merge_into or out")
        results = Results.start(command, s.quick, asdict(s))
    with tempfile.TemporaryDirectory(prefix="vtzero-train-bench-") as tmp_name:
        tmp = Path(tmp_name)
        measure = {
            "encode_torch": lambda: encode_torch_phase(s, models),
            "train": lambda: train_phase(s, tmp, models),
        }
        for phase in phases:
            results.run_phase(phase, measure[phase])
    md = results.write(out, WHY)
    print(md)
    progress(f"wrote {out / 'results.json'} and {out / 'results.md'} in "
             f"{results.run['duration_s']:.0f} s (both sides)")
    return 0
