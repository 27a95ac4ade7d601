"""``vt-train``: offline training, export, reference database, evaluation and release.

The shipped ``models/`` comes from one command::

    vt-train release            # = python -m train release --out models --seed 0
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
from collections.abc import Sequence
from pathlib import Path

from edge import __version__
from edge.core.errors import EdgeError, EvalVLMError
from edge.core.logs import setup_logging

log = logging.getLogger(__name__)

# The modules only the `train` extra installs (pyproject.toml).
TRAIN_EXTRA_MODULES = ("torch", "onnx", "matplotlib")


def _cmd_record(args: argparse.Namespace) -> int:
    from edge.core.progress import Progress
    from edge.lab.record import record_dataset
    from edge.sim.catalogue import DATASETS

    total = len(DATASETS[args.dataset]) * args.presses
    with Progress(f"record {args.dataset}", total, "presses") as bar:
        index = record_dataset(args.dataset, args.presses, args.out, seed=args.seed,
                               workers=args.workers, progress=lambda done, _t: bar.set(done))
    print(f"wrote {len(index['classes']) * args.presses} presses of "
          f"{len(index['classes'])} classes ({args.dataset}) to {args.out}")
    return 0


def _splits(args: argparse.Namespace):
    from train.learn.data import Splits

    return Splits.from_file(args.splits) if args.splits else None


def _cmd_train(args: argparse.Namespace) -> int:
    from train.learn.data import training_data
    from train.learn.model import ModelConfig
    from train.learn.trainer import CHECKPOINT, TRAIN_LOG, Progress, TrainConfig, train

    data = training_data(args.recordings, _splits(args))
    config = TrainConfig(
        model=ModelConfig(variant=args.variant, revive_dead=not args.no_revive,
                          decoder=args.decoder),
        seed=args.seed, max_epochs=args.max_epochs, patience=args.patience,
        threads=args.threads)
    result = train(data, config, args.out, Progress(enabled=not args.quiet))
    print(json.dumps(result.summary() | {"seconds": round(result.seconds, 1)}))
    print(f"best checkpoint: {Path(args.out) / CHECKPOINT}; log: {Path(args.out) / TRAIN_LOG}")
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    import numpy as np

    from edge.core.model import ENCODER_FILE
    from train.learn.data import load_presses
    from train.learn.trainer import load_checkpoint
    from train.ship.export import check_parity, export_onnx, parity

    model, norm, _ = load_checkpoint(args.checkpoint)
    out = Path(args.out)
    path = out / ENCODER_FILE if out.is_dir() or not out.suffix else out
    data = export_onnx(model, norm, path)
    real = load_presses(args.recordings).inputs(0) if args.recordings else np.zeros((0,))
    result = parity(model, norm, data, real if len(real) else None)
    check_parity(result)
    print(f"wrote {path} ({len(data)} bytes); parity onnxruntime vs torch: max |dz| "
          f"{result.max_abs_z:.3g} over {result.cases} inputs, "
          f"{result.code_mismatches} code mismatches")
    return 0


def _cmd_db_build(args: argparse.Namespace) -> int:
    from train.ship.database import build_into

    db = build_into(args.model, args.recordings, _splits(args), args.space, args.k)
    print(f"database: {len(db)} references of {len(db.classes)} classes in {args.model}")
    return 0


def _cmd_db_add(args: argparse.Namespace) -> int:
    from train.ship.database import add_class

    db = add_class(args.model, args.recordings, args.label, args.description,
                   relabel=args.relabel, force=args.force, allow_test=args.allow_test)
    print(f"added {args.label!r}; database: {len(db)} references of {len(db.classes)} classes")
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    from edge.core.model import load_model
    from train.eval import evaluate
    from train.learn.data import PressSet, Splits, load_presses
    from train.learn.trainer import embed, load_checkpoint

    model = load_model(args.model, any_sensor=True)  # a model of any sensor is evaluated
    splits = _splits(args) or Splits.of_dataset(args.reference)
    reference = load_presses(args.reference, splits.classes).select(splits.classes)
    unseen = PressSet.concat(*(load_presses(d) for d in args.unseen))
    codebook = model.database.codebook
    embedders = {"vq": (evaluate.onnx_embedder(model.encoder, codebook), codebook)}
    if args.paper:
        paper, paper_norm, _ = load_checkpoint(args.paper)
        assert paper.quantiser is not None
        embedders["vq_paper"] = ((lambda x: embed(paper, paper_norm, x)),
                                 paper.quantiser.codebook.detach().numpy().copy())
    if args.zeros:
        zeros, zeros_norm, _ = load_checkpoint(args.zeros)
        assert zeros.quantiser is not None
        embedders["vq_zeros"] = ((lambda x: embed(zeros, zeros_norm, x)),
                                 zeros.quantiser.codebook.detach().numpy().copy())
    if args.beta:
        beta, norm, _ = load_checkpoint(args.beta)
        embedders["beta"] = ((lambda x: embed(beta, norm, x)), None)
    report = evaluate.evaluate(embedders, reference, splits, unseen, args.out, k=args.k,
                               seed=args.seed)
    print((Path(args.out) / "eval.md").read_text())
    m = evaluate.summary_metrics(report)
    print(f"kiri mochi AUC (raw vs boiled): {m['kiri_mochi_auc']}")
    return 0


def _cmd_eval_vlm(args: argparse.Namespace) -> int:
    import asyncio

    from train.eval import eval_vlm
    from train.eval.eval_vlm.cache import ANSWERS_FILE, AnswerCache
    from train.eval.eval_vlm.config import DEFAULT_CONDITIONS, EvalVLMConfig
    from train.eval.eval_vlm.paper import parse_paper_sets
    from train.eval.eval_vlm.plan import describe_plan, prepare
    from train.eval.eval_vlm.provenance import model_facts, variant_advice
    from train.eval.eval_vlm.report import REPORT_JSON, REPORT_MD, slug
    from train.ship.manifest import read_raw

    vlm = _vlm_settings(args)
    conditions = tuple(c.strip() for c in args.conditions.split(",") if c.strip()) \
        if args.conditions else DEFAULT_CONDITIONS
    paths = _comparisons(args)
    beta, zeros, reference = paths["beta"], paths["zeros"], paths["reference"]
    if not args.conditions and "beta_top3" in conditions and not (
            beta and beta.exists() and reference and reference.exists()):
        facts = model_facts(read_raw(Path(args.model_dir)))
        log.warning("no beta-VAE checkpoint (%s) or reference recordings (%s): skipping the "
                    "beta_top3 condition (train it with %s)", beta, reference,
                    variant_advice(facts, Path(args.model_dir), "beta"))
        conditions = tuple(c for c in conditions if c != "beta_top3")
    out = Path(args.out) if args.out else Path("runs/eval-vlm") / slug(vlm.model)
    cfg = EvalVLMConfig(
        vlm=vlm, out=out, unseen=tuple(Path(d) for d in args.unseen),
        model_dir=Path(args.model_dir), conditions=conditions, reference=reference,
        beta=beta, zeros=zeros, images=Path(args.images) if args.images else None,
        limit=args.limit, concurrency=args.concurrency,
        paper_sets=parse_paper_sets(args.paper_set))
    if not args.verbose:  # one INFO line per answer from the client is too much here
        logging.getLogger("edge.vlm").setLevel(logging.WARNING)
    if args.dry_run:
        plan = prepare(cfg, endpoint=False)
        cache = AnswerCache(out / ANSWERS_FILE)
        print(describe_plan(plan, cache.load()))
        return 0
    asyncio.run(eval_vlm.run(cfg, progress=not args.quiet))
    print((out / REPORT_MD).read_text())
    print(f"answers: {out / ANSWERS_FILE}; report: {out / REPORT_JSON}")
    return 0


def _vlm_settings(args: argparse.Namespace):
    from edge.core.config import VLMConfig, load_config

    vlm = load_config(args.config).vlm if args.config else VLMConfig()
    overrides: dict = {k: v for k, v in (("base_url", args.url), ("model", args.model))
                       if v is not None}
    if args.prompt_dir:
        overrides["prompt_dir"] = Path(args.prompt_dir)
    return dataclasses.replace(vlm, **overrides)


RELEASE_DEFAULTS = {"reference": "runs/release/recordings/reference",
                    "beta": "runs/release/beta/checkpoint.pt",
                    "zeros": "runs/release/vq_zeros/checkpoint.pt"}
DEFAULTS_HELP = {
    "reference": "the dataset a `vt-train build` model was built from, else "
                 + RELEASE_DEFAULTS["reference"],
    "beta": "MODEL_DIR/training/beta/checkpoint.pt (vt-train build --variant beta), else "
            + RELEASE_DEFAULTS["beta"],
    "zeros": "MODEL_DIR/training/vq_zeros/checkpoint.pt (vt-train build --variant zeros), "
             "else " + RELEASE_DEFAULTS["zeros"]}


def _comparisons(args: argparse.Namespace) -> dict[str, Path | None]:
    """--reference, --beta, --zeros as given, else what a model directory `vt-train build`
    made holds (its dataset, its comparison checkpoints; None where it has none), else (the
    simulated release) the release's."""
    from train.eval.eval_vlm.provenance import model_facts
    from train.ship.build import checkpoints
    from train.ship.manifest import read_raw

    model_dir = Path(args.model_dir)
    manifest = read_raw(model_dir) if model_dir.is_dir() else {}
    given = {name: getattr(args, name, None) for name in RELEASE_DEFAULTS}
    if not model_facts(manifest)["built"]:
        return {name: Path(given[name] or default) for name, default in
                RELEASE_DEFAULTS.items()}
    kept = checkpoints(model_dir)
    data = manifest.get("training", {}).get("dataset", {}).get("directory")
    found = {"reference": data, "beta": kept.get("beta"), "zeros": kept.get("vq_zeros")}
    return {name: Path(given[name] or found[name]) if given[name] or found[name] else None
            for name in RELEASE_DEFAULTS}


def _reference(args: argparse.Namespace) -> Path:
    reference = _comparisons(args)["reference"]
    if reference is None:
        raise EvalVLMError(f"{args.model_dir} records no dataset it was built from: give "
                           "--reference DATASET")
    return reference


def _cmd_table1(args: argparse.Namespace) -> int:
    import asyncio

    from train.eval import table1
    from train.eval.eval_vlm.paper import parse_paper_sets

    first = _vlm_settings(args)
    second = None
    if args.second_model:
        second = dataclasses.replace(first, model=args.second_model,
                                     **({"base_url": args.second_url} if args.second_url
                                        else {}))
    paths = _comparisons(args)
    cfg = table1.Table1Config(
        first=first, second=second, out=Path(args.out), work=Path(args.work),
        unseen=tuple(Path(d) for d in args.unseen), model_dir=Path(args.model_dir),
        reference=paths["reference"], beta=paths["beta"], zeros=paths["zeros"],
        images=Path(args.images) if args.images else None, limit=args.limit,
        concurrency=args.concurrency, extras=not args.no_extras,
        rows=tuple(args.rows) if args.rows else None,
        paper_sets=parse_paper_sets(args.paper_set))
    table1.validate(cfg)
    if not args.verbose:
        logging.getLogger("edge.vlm").setLevel(logging.WARNING)
    asyncio.run(table1.run(cfg, progress=not args.quiet))
    print((cfg.out / table1.REPORT_MD).read_text())
    return 0


def _cmd_fig6(args: argparse.Namespace) -> int:
    import asyncio

    from train.eval import fig6
    from train.eval.eval_vlm.paper import parse_paper_sets

    cfg = fig6.Fig6Config(
        vlm=_vlm_settings(args), out=Path(args.out), work=Path(args.work),
        reference=_reference(args), unseen=tuple(Path(d) for d in args.unseen),
        model_dir=Path(args.model_dir),
        sizes=tuple(int(n) for n in args.sizes.split(",") if n.strip()), draws=args.draws,
        seed=args.seed, max_epochs=args.max_epochs, patience=args.patience,
        decoder=args.decoder, images=Path(args.images) if args.images else None,
        limit=args.limit, concurrency=args.concurrency,
        paper_sets=parse_paper_sets(args.paper_set))
    if not args.verbose:
        logging.getLogger("edge.vlm").setLevel(logging.WARNING)
    asyncio.run(fig6.run(cfg, progress=not args.quiet))
    print((cfg.out / fig6.REPORT_MD).read_text())
    return 0


def _cmd_release(args: argparse.Namespace) -> int:
    from train.learn.trainer import Progress
    from train.ship.release import ReleaseConfig, release

    cfg = ReleaseConfig(out=Path(args.out), work=Path(args.work),
                        recordings=Path(args.recordings) if args.recordings else None,
                        seed=args.seed,
                        presses=args.presses, unseen_presses=args.unseen_presses,
                        max_epochs=args.max_epochs, patience=args.patience,
                        beta=not args.no_beta, zeros=not args.no_zeros,
                        paper=not args.no_paper, workers=args.workers,
                        std_floor=args.std_floor)
    manifest = release(cfg, Progress(enabled=not args.quiet))
    m = manifest["metrics"]
    print(f"released {cfg.out}: kiri mochi AUC {m['kiri_mochi_auc']}, LOO 1-NN "
          f"{m['loo_1nn']:.3f}, VQ best epoch {m['vq_best_epoch']} of {m['vq_epochs']}; "
          f"report {cfg.out / 'eval' / 'eval.md'}")
    return 0


def _cmd_build(args: argparse.Namespace) -> int:
    from train.learn.trainer import Progress
    from train.ship.build import SHIPPED_PROMPTS, BuildConfig, build

    cfg = BuildConfig(data=Path(args.data), out=Path(args.out),
                      variants=tuple(dict.fromkeys(args.variant or ())),
                      unseen=tuple(Path(u) for u in args.unseen or ()),
                      prompts=Path(args.prompts) if args.prompts else SHIPPED_PROMPTS,
                      seed=args.seed, max_epochs=args.max_epochs, patience=args.patience,
                      threads=args.threads, mixed_rates=args.mixed_rates,
                      std_floor=args.std_floor, embedding=args.embedding, seeds=args.seeds)
    manifest = build(cfg, Progress(enabled=not args.quiet))
    m = manifest["metrics"]
    base = m["comparison"].get("baseline/z", {})
    print(f"built {cfg.out} from {cfg.data} ({manifest['origin']['kind']} data, embedding "
          f"{manifest['encoder']['embedding']}{'' if cfg.embedding else ' (chosen)'}): "
          f"{manifest['database']['references']} references of "
          f"{manifest['database']['classes']} classes; LOO 1-NN {m['loo_1nn']:.3f} "
          f"(trivial baseline {base.get('loo_1nn', float('nan')):.3f}); report "
          f"{cfg.out / 'eval' / 'eval.md'}; " + (
              "load it with SIGHUP (systemctl reload vtzero-edge) where [runtime] models_dir "
              "names it" if manifest.get("sequences") is None else
              "another sensor's model: `vt-train eval` reads it, the robot's daemon refuses it"))
    return 0


def _cmd_transfer(args: argparse.Namespace) -> int:
    from train.eval.transfer import REPORT_JSON, REPORT_MD, TransferConfig, run

    cfg = TransferConfig(data=Path(args.data), partners=Path(args.partners),
                         out=Path(args.out), format=args.format,
                         candidates=tuple(c.strip() for c in args.candidates.split(",")
                                          if c.strip()),
                         seeds=args.seeds, max_epochs=args.max_epochs, patience=args.patience,
                         std_floor=args.std_floor, threads=args.threads)
    if not args.verbose:  # a line per training is too much beside the progress line
        logging.getLogger("train.learn.trainer").setLevel(logging.WARNING)
    run(cfg, progress=not args.quiet)
    print((cfg.out / REPORT_MD).read_text())
    print(f"report: {cfg.out / REPORT_MD}, {cfg.out / REPORT_JSON}")
    return 0


def _cmd_convert(args: argparse.Namespace) -> int:
    from train.learn import phac2

    written = phac2.convert(args.data, args.out)
    print(f"wrote {len(written)} sequences of {len({p.parent.name for p in written})} objects "
          f"to {args.out}")
    return 0


def _cmd_rehash(args: argparse.Namespace) -> int:
    from train.ship.manifest import read_raw, write_manifest

    reports = [name for name in read_raw(Path(args.model)).get("reports", {})
               if (Path(args.model) / name).exists()]
    manifest = write_manifest(args.model, reports=reports)
    print(f"re-hashed {len(manifest['files'])} files in {Path(args.model) / 'manifest.json'}")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from train.eval.bench import FULL, QUICK, bench

    return bench(QUICK if args.quick else FULL, models=Path(args.model),
                 merge_into=Path(args.merge_into) if args.merge_into else None,
                 out=Path(args.out))


def build_parser() -> argparse.ArgumentParser:
    from train.learn.data import STD_FLOOR_FRACTION  # numpy only: no training stack

    parser = argparse.ArgumentParser(prog="vt-train", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"vtzero {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("record", help="record a simulated dataset (the edge recorder)")
    p.add_argument("--dataset", required=True, choices=["reference", "foodreplica", "cube"])
    p.add_argument("--presses", type=int, default=10, help="presses per class")
    p.add_argument("--out", required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=None)
    p.set_defaults(func=_cmd_record)

    p = sub.add_parser("train", help="train the VQ-VAE (or the beta-VAE)")
    p.add_argument("--recordings", required=True, help="reference recordings directory")
    p.add_argument("--splits", help="class splits (default: the recordings' dataset.json)")
    p.add_argument("--out", required=True, help="directory for checkpoint.pt and train.jsonl")
    p.add_argument("--variant", choices=["vq", "beta"], default="vq")
    p.add_argument("--decoder", choices=["teacher", "zeros"], default="teacher",
                   help="teacher: the paper's decoder (z_q and X, teacher-forced; default); "
                   "zeros: z_q alone, zero inputs (the comparison variant)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-epochs", type=int, default=300)
    p.add_argument("--patience", type=int, default=25)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--no-revive", action="store_true", help="leave dead codes dead")
    p.add_argument("-q", "--quiet", action="store_true")
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("export", help="export a VQ checkpoint's encoder to ONNX")
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--out", required=True, help="model directory or .onnx path")
    p.add_argument("--recordings", help="recordings for the parity check on real inputs")
    p.set_defaults(func=_cmd_export)

    db = sub.add_parser("db", help="the reference database")
    dbsub = db.add_subparsers(dest="db_command", required=True)
    p = dbsub.add_parser("build", help="encode the reference presses with MODEL's encoder")
    p.add_argument("--model", required=True,
                   help="model directory (its encoder: encoder.onnx, or encoder.npz of kind mean)")
    p.add_argument("--recordings", required=True)
    p.add_argument("--splits")
    p.add_argument("--space", choices=["z", "z_q"], default="z")
    p.add_argument("--k", type=int, default=3)
    p.set_defaults(func=_cmd_db_build)
    p = dbsub.add_parser("add", help="add a class's presses without retraining")
    p.add_argument("--model", required=True)
    p.add_argument("--recordings", required=True)
    p.add_argument("--label", required=True)
    p.add_argument("--description", required=True)
    p.add_argument("--relabel", action="store_true",
                   help="file presses labelled otherwise in their metadata under --label")
    p.add_argument("--force", action="store_true",
                   help="add presses made at a threshold unlike the database's classes'")
    p.add_argument("--allow-test", action="store_true",
                   help="add presses their dataset.json splits test (the manifest records it, "
                   "and Table I says so)")
    p.set_defaults(func=_cmd_db_add)

    p = sub.add_parser("eval", help="retrieval quality on unseen classes, pictures, tables")
    p.add_argument("--model", required=True)
    p.add_argument("--reference", required=True, help="reference recordings")
    p.add_argument("--unseen", required=True, nargs="+", help="unseen-class recordings")
    p.add_argument("--out", required=True)
    p.add_argument("--beta", help="beta-VAE checkpoint for the comparison")
    p.add_argument("--zeros", help="checkpoint of the VQ-VAE with the zero-input decoder, "
                   "for the comparison")
    p.add_argument("--paper", help="checkpoint of the VQ-VAE in the paper's configuration "
                   "(z of 4, no metric term), for the comparison")
    p.add_argument("--splits")
    p.add_argument("--k", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_eval)

    p = sub.add_parser(
        "eval-vlm", help="the paper's Table I against an OpenAI-compatible VLM endpoint",
        description="Ask a VLM about every unseen test press under each condition (vision "
        "only; vision + tactile top-3 / top-1 with the VQ-VAE; top-3 with the beta-VAE), "
        "with the robot's own prompts and client; answers are cached, so an interrupted run "
        "continues. The API key comes from $VTZERO_VLM_API_KEY (or the [vlm] section of "
        "--config).")
    p.add_argument("--url", help="endpoint up to /v1, e.g. https://api.openai.com/v1, "
                   "http://localhost:8000/v1 (vLLM), http://localhost:11434/v1 (Ollama)")
    p.add_argument("--model", help="the VLM model name the endpoint knows")
    p.add_argument("--config", help="a vt-edge TOML config whose [vlm] section gives the "
                   "defaults (key file, timeouts, seed); --url/--model override it")
    p.add_argument("--prompt-dir", help="prompt templates (default: models/prompts)")
    p.add_argument("--model-dir", default="models", help="the tactile model directory")
    p.add_argument("--unseen", nargs="+", default=[
        "runs/release/recordings/foodreplica", "runs/release/recordings/cube"],
        help="unseen test sets, one recordings directory each (default: the release's)")
    p.add_argument("--reference", help="reference recordings (the beta-VAE's database; "
                   f"default: {DEFAULTS_HELP['reference']})")
    p.add_argument("--beta", help=f"beta-VAE checkpoint (default: {DEFAULTS_HELP['beta']})")
    p.add_argument("--zeros", help="checkpoint of the VQ-VAE with the zero-input decoder "
                   f"(default: {DEFAULTS_HELP['zeros']})")
    p.add_argument("--conditions", help="comma-separated, from: vision_only, vq_top3, "
                   "vq_top1, beta_top3, vq_zeros_top3, vq_top3_adjectives, tactile_only "
                   "(default: the first four)")
    p.add_argument("--images", help="photos for real data: <press name>.jpg or <label>.jpg "
                   "(.jpeg, .png) in DIR/<set>/ or DIR/ (default: the photo collect took "
                   "beside each press, else the simulated camera)")
    p.add_argument("--paper-set", action="append", default=[], metavar="NAME=PAPER_SET",
                   help="stand set NAME beside the paper's foodreplica or cube (repeatable)")
    p.add_argument("--limit", type=int, help="at most N presses per set (round-robin over "
                   "classes), for a quick run")
    p.add_argument("--concurrency", type=int, default=4, help="requests in flight")
    p.add_argument("--out", help="output and answer cache (default runs/eval-vlm/<model>)")
    p.add_argument("--dry-run", action="store_true",
                   help="print the questions and one prompt per condition; ask nothing")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=_cmd_eval_vlm)

    p = sub.add_parser(
        "table1", help="the paper's Table I (two models) against an endpoint or the "
        "simulated VLM", description="Vision only, VQ-VAE top-3, top-1 and the beta-VAE "
        "(and, when their checkpoints exist, the zero-input decoder and the tactile-adjective "
        "ablation) on FoodReplica and Cube for two models, beside the paper's GPT-4V and "
        "LLaVA numbers. Without --url the simulated VLM answers (simulated-vlm and "
        "simulated-vlm-vision-led). Answers are cached per model under --work: run it again "
        "to continue.")
    p.add_argument("--url", help="endpoint up to /v1 (default: the simulated VLM)")
    p.add_argument("--model", help="the first model (the paper's GPT-4V rows)")
    p.add_argument("--second-model", help="the second model (the paper's LLaVA rows)")
    p.add_argument("--second-url", help="the second model's endpoint (default --url)")
    p.add_argument("--config", help="a vt-edge TOML config whose [vlm] section gives the "
                   "defaults (key file, timeouts, seed)")
    p.add_argument("--prompt-dir", help="prompt templates (default: models/prompts)")
    p.add_argument("--model-dir", default="models")
    p.add_argument("--unseen", nargs="+", default=[
        "runs/release/recordings/foodreplica", "runs/release/recordings/cube"])
    p.add_argument("--reference", help=f"default: {DEFAULTS_HELP['reference']}")
    p.add_argument("--beta", help=f"default: {DEFAULTS_HELP['beta']}")
    p.add_argument("--zeros", help=f"default: {DEFAULTS_HELP['zeros']}")
    p.add_argument("--paper-set", action="append", default=[], metavar="NAME=PAPER_SET",
                   help="stand set NAME beside the paper's foodreplica or cube (repeatable; "
                   "sets so named stand beside them unasked)")
    p.add_argument("--no-extras", action="store_true",
                   help="only the paper's rows (no zero-input decoder or ablation rows)")
    p.add_argument("--rows", nargs="+", metavar="ROW",
                   help="ask only these rows (e.g. vq_top3 vq_top3_weak: an ablation beside "
                   "its twin against a real endpoint); default every row that can run")
    p.add_argument("--images", help="photos for real data (as eval-vlm --images; default: "
                   "the photo collect took beside each press)")
    p.add_argument("--limit", type=int, help="at most N presses per set")
    p.add_argument("--concurrency", type=int, default=4)
    p.add_argument("--work", default="runs/table1", help="answer caches, one per model")
    p.add_argument("--out", default="runs/table1", help="table1.md, table1.json, PNGs "
                   "(the shipped stand-in results: models/eval/table1)")
    p.add_argument("-q", "--quiet", action="store_true")
    p.set_defaults(func=_cmd_table1)

    p = sub.add_parser(
        "fig6", help="the paper's Fig. 6: accuracy against the number of reference classes",
        description="For each |Y_ref| (default 0, 6, 13, 20, 27) and draw (default 5): draw "
        "the classes, retrain the encoder on them, build a database without the validation "
        "classes, ask the VLM (vision + tactile, top-3) about every unseen press; mean and "
        "std per size as a table and a plot. Trainings and answers are cached under --work: "
        "run it again to continue. Without --url the simulated VLM answers.")
    p.add_argument("--url", help="endpoint up to /v1 (default: the simulated VLM)")
    p.add_argument("--model", help="the VLM model name")
    p.add_argument("--config", help="a vt-edge TOML config whose [vlm] section gives the "
                   "defaults")
    p.add_argument("--prompt-dir", help="prompt templates (default: models/prompts)")
    p.add_argument("--model-dir", default="models",
                   help="the shipped model (its decoder and window are copied)")
    p.add_argument("--reference", help=f"default: {DEFAULTS_HELP['reference']}")
    p.add_argument("--unseen", nargs="+", default=[
        "runs/release/recordings/foodreplica", "runs/release/recordings/cube"])
    p.add_argument("--paper-set", action="append", default=[], metavar="NAME=PAPER_SET",
                   help="stand set NAME beside the paper's foodreplica or cube (repeatable)")
    p.add_argument("--sizes", default="0,6,13,20,27", help="|Y_ref| values, comma-separated")
    p.add_argument("--draws", type=int, default=5)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-epochs", type=int, default=100)
    p.add_argument("--patience", type=int, default=10)
    p.add_argument("--decoder", choices=["teacher", "zeros"],
                   help="default: the shipped model's")
    p.add_argument("--images", help="photos for real data (as eval-vlm --images; default: "
                   "the photo collect took beside each press)")
    p.add_argument("--limit", type=int, help="at most N presses per set")
    p.add_argument("--concurrency", type=int, default=4)
    p.add_argument("--work", default="runs/fig6", help="trainings and answer cache")
    p.add_argument("--out", default="runs/fig6", help="fig6.md, fig6.json, fig6.png "
                   "(the shipped stand-in results: models/eval/fig6)")
    p.add_argument("-q", "--quiet", action="store_true")
    p.set_defaults(func=_cmd_fig6)

    p = sub.add_parser("release", help="regenerate models/ from the simulated reference set")
    p.add_argument("--out", default="models")
    p.add_argument("--work", default="runs/release", help="recordings and training runs")
    p.add_argument("--recordings", help="where the simulated recordings live or go "
                   "(default WORK/recordings; reused when seed and presses match)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--presses", type=int, default=10)
    p.add_argument("--unseen-presses", type=int, default=10)
    p.add_argument("--max-epochs", type=int, default=300)
    p.add_argument("--patience", type=int, default=25)
    p.add_argument("--no-beta", action="store_true", help="skip the beta-VAE comparison")
    p.add_argument("--no-zeros", action="store_true",
                   help="skip the zero-input decoder comparison")
    p.add_argument("--no-paper", action="store_true",
                   help="skip the paper's configuration (z of 4, no metric term)")
    p.add_argument("--workers", type=int, default=None, help="recorder processes")
    p.add_argument("--std-floor", type=float, default=STD_FLOOR_FRACTION,
                   help="the normaliser's floor, a fraction of the RMS of the channel stds "
                   "(default %(default)s)")
    p.add_argument("-q", "--quiet", action="store_true")
    p.set_defaults(func=_cmd_release)

    p = sub.add_parser(
        "build", help="a deployable model directory from a collected dataset (the lab's own "
        "presses)", description="Train the VQ-VAE (the paper's decoder), export it to ONNX "
        "(parity-checked), build the database of every offset of every press of the train "
        "and val classes, copy and hash the prompt templates, evaluate retrieval beside a "
        "trivial baseline (on the dataset's test classes and --unseen sets) and write the "
        "manifest with the data's origin. Each step is kept in OUT.partial with the hash of "
        "its inputs: run it again to continue. OUT is replaced at the end (the old one is "
        "kept as OUT.previous).")
    p.add_argument("--data", required=True, help="dataset directory (vt-edge collect --plan)")
    p.add_argument("--out", required=True, help="model directory to write")
    p.add_argument("--variant", action="append", choices=["beta", "zeros", "paper"],
                   help="also train this comparison variant (repeatable): the beta-VAE, the "
                   "zero-input decoder, the paper's configuration (z of 4, no metric term); "
                   "their rows join the evaluation (beta, zeros: and Table I)")
    p.add_argument("--embedding", choices=["shipped", "paper", "mean"],
                   help="deploy this embedding and train no other: shipped (z of 16 and the "
                   "metric term), paper (z of 4, reconstruction only) or mean (each "
                   "channel's mean over the window after the normaliser: no training, "
                   "served with numpy). Default: all three are tried and the one whose "
                   "validation classes' presses find their own class best wins (eval.md "
                   "says by how much)")
    p.add_argument("--seeds", type=int, default=1,
                   help="seeds each candidate is trained with for the choice (default "
                   "%(default)s; 2 or more give a spread to judge the difference by)")
    p.add_argument("--unseen", nargs="+", help="further test sets for the evaluation")
    p.add_argument("--prompts", help="prompt templates to ship (default: models/prompts)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-epochs", type=int, default=300)
    p.add_argument("--patience", type=int, default=25)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--mixed-rates", action="store_true",
                   help="build from classes pressed at stream rates more than 10%% apart "
                   "(refused by default: they embed the same object in two places)")
    p.add_argument("--std-floor", type=float, default=STD_FLOOR_FRACTION,
                   help="the normaliser's floor on each channel's spread, a fraction of the "
                   "RMS of all channels' (default %(default)s, for XELA pads' noise channels; "
                   "0: each channel its own); the manifest records it")
    p.add_argument("-q", "--quiet", action="store_true")
    p.set_defaults(func=_cmd_build)

    p = sub.add_parser(
        "transfer", help="does touch transfer? leave one object out over seeds, neighbours "
        "scored against a partner file", description="For each object and seed, fit each "
        "candidate embedding on the other objects, retrieve each of its presses' first "
        "neighbour and top 3 among them and score them against the partner file (JSON: object "
        "-> objects that feel like it); LOO 1-NN among the seen objects; beside chance, with "
        "the seed spread. Writes transfer.md and transfer.json.")
    p.add_argument("--data", required=True, help="press recordings and/or .seq.npz sequences "
                   "(any depth), or PHAC-2 .mat files with --format phac2")
    p.add_argument("--format", choices=["presses", "phac2"], default="presses")
    p.add_argument("--partners", required=True,
                   help='JSON: {"object": ["partner", ...], ...}')
    p.add_argument("--out", default="runs/transfer")
    p.add_argument("--candidates", default="shipped,paper,mean",
                   help="comma-separated: shipped (z of 16, metric term), paper (z of 4, "
                   "reconstruction only), mean (each channel's mean over the window), "
                   "physics (the press's peak, stiffness, relaxation, spread), mean+physics")
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--max-epochs", type=int, default=300)
    p.add_argument("--patience", type=int, default=25)
    p.add_argument("--std-floor", type=float, default=STD_FLOOR_FRACTION,
                   help="the normaliser's floor on each channel's spread, a fraction of the "
                   "RMS of all channels' (default %(default)s, for XELA pads' noise channels; "
                   "0: each channel its own)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("-q", "--quiet", action="store_true")
    p.set_defaults(func=_cmd_transfer)

    p = sub.add_parser("convert", help="other sensors' data into labelled sequences "
                       "(.seq.npz, one per press)")
    p.add_argument("--format", choices=["phac2"], required=True)
    p.add_argument("--data", required=True, help="the files to convert")
    p.add_argument("--out", required=True, help="directory for OBJECT/NAME.seq.npz")
    p.set_defaults(func=_cmd_convert)

    p = sub.add_parser("rehash", help="re-hash a model directory after a deliberate edit")
    p.add_argument("--model", required=True)
    p.set_defaults(func=_cmd_rehash)

    p = sub.add_parser("bench", help="the bench's torch and training figures "
                       "(after vt-edge bench: --merge-into bench/results.json)")
    p.add_argument("--model", default="models", help="model directory (default models)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--merge-into", metavar="RESULTS_JSON",
                       help="add the figures to this results.json of vt-edge bench (and "
                       "render its results.md again)")
    where.add_argument("--out", default="bench",
                       help="directory for a results file of its own (default bench)")
    p.add_argument("--quick", action="store_true",
                   help="short runs (a smoke test; figures are not representative)")
    p.set_defaults(func=_cmd_bench)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(logging.DEBUG if args.verbose else logging.INFO)
    try:
        return int(args.func(args) or 0)
    except (EdgeError, ValueError) as exc:
        log.error("%s", exc)
        return 2
    except ModuleNotFoundError as exc:
        # An edge-only install (vtzero[edge]) has no training stack; any other missing
        # module is a broken install and keeps its traceback.
        if (exc.name or "").split(".")[0] not in TRAIN_EXTRA_MODULES:
            raise
        command = " ".join(filter(None, (args.command, getattr(args, "db_command", None))))
        log.error("vt-train %s needs the training extra (no module %r): "
                  "pip install 'vtzero[train]'", command, exc.name)
        return 2
    except KeyboardInterrupt:
        return 130

