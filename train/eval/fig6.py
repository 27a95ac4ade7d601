"""``vt-train fig6``: the paper's Fig. 6, accuracy against the size of the reference set.

For |Y_ref| in (0, 6, 13, 20, 27) reference classes and 5 random draws each: draw |Y_ref|
of the 27 training classes, retrain the encoder on them (the 5 validation classes still
decide early stopping), build a database of the drawn classes only (every offset of every
press; the validation classes are left out, as in the paper), and ask the VLM the method's
question (vision + tactile, top-3) about every unseen press. |Y_ref| = 0 is vision only.
Reported per size and set: the mean and standard deviation (sample, ddof = 1) of the
accuracy over the draws, as ``fig6.md``, ``fig6.json`` and ``fig6.png``, with the paper's
two known end points (vision only and the full set, its Table I) beside them; the paper
showed no clear trend between them.

Draws are seeded (``SeedSequence([seed, size, draw])``), and so is each training: at 27
classes every draw holds the same classes and differs only in its training seed.

Resumable and cached: each training is kept in ``WORK/n<size>_d<draw>/`` (checkpoint,
``train.jsonl``, ``result.json`` with the key it was made for: classes, seed, epochs,
model configuration and a digest of the reference data); a rerun loads it instead of training again.
Answers go to ``WORK/<model>/answers.jsonl`` (:class:`train.eval.eval_vlm.cache.AnswerCache`):
a question already answered (the same prompt and photo) is never asked again, whichever draw
asks it.
With no ``--url`` the simulated VLM answers (``simulated-vlm``).

Training time sets the command's length: ``--max-epochs`` and ``--patience`` default to 100
and 10 here (the release uses 300 and 25) so the 20 trainings take minutes, not an hour.
"""

from __future__ import annotations

import asyncio
import dataclasses
import hashlib
import json
import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from edge.core.atomic import atomic_write_text
from edge.core.config import VLMConfig
from edge.core.errors import EvalVLMError
from edge.core.model import read_manifest
from edge.core.preprocess import DEFAULT_WINDOW, WindowSpec
from edge.core.progress import Progress as Bar
from edge.vlm.prompt import load_template
from train.eval.eval_vlm.ask import EvalProgress, ask_all
from train.eval.eval_vlm.cache import ANSWERS_FILE, AnswerCache
from train.eval.eval_vlm.config import CONDITIONS, DEFAULT_CONCURRENCY, EvalVLMConfig
from train.eval.eval_vlm.images import ImageSource
from train.eval.eval_vlm.paper import paper_set, set_title
from train.eval.eval_vlm.plan import Job, Plan, build_jobs
from train.eval.eval_vlm.provenance import decoder_title, describe_origin, reference_origin
from train.eval.eval_vlm.report import save_png, slug
from train.eval.eval_vlm.sets import load_sets
from train.eval.eval_vlm.tactile import load_reference, torch_tactile
from train.learn.data import STD_FLOOR_FRACTION, PressSet, Splits, training_data_of
from train.learn.model import ModelConfig
from train.learn.trainer import CHECKPOINT, Progress, TrainConfig, load_checkpoint, train

log = logging.getLogger(__name__)

SIZES = (0, 6, 13, 20, 27)
DRAWS = 5
RESULT = "result.json"
RESULT_FORMAT = "vtzero-fig6-run-1"
REPORT_MD = "fig6.md"
REPORT_JSON = "fig6.json"
REPORT_PNG = "fig6.png"
# The paper's end points (GPT-4V, Table I): vision only (|Y_ref| = 0) and the full set (27).
PAPER_ENDS = {0: {"foodreplica": 53.6, "cube": 50.0}, 27: {"foodreplica": 58.9, "cube": 65.0}}
DPI = 80


@dataclass(frozen=True)
class Fig6Config:
    vlm: VLMConfig  # base_url "" = the simulated VLM
    out: Path
    work: Path
    reference: Path
    unseen: tuple[Path, ...]
    model_dir: Path = Path("models")  # its decoder choice and window; the prompts
    sizes: tuple[int, ...] = SIZES
    draws: int = DRAWS
    seed: int = 0
    max_epochs: int = 100
    patience: int = 10
    decoder: str | None = None  # None: the shipped model's
    threads: int = 1
    images: Path | None = None
    limit: int | None = None
    concurrency: int = DEFAULT_CONCURRENCY
    paper_sets: Mapping[str, str] = dataclasses.field(default_factory=dict)  # ours -> paper's

    @property
    def standin(self) -> bool:
        return not self.vlm.configured

    def validate(self, train_classes: int) -> None:
        if self.draws < 1:
            raise EvalVLMError(f"--draws must be >= 1, got {self.draws}")
        bad = [n for n in self.sizes if not 0 <= n <= train_classes]
        if bad or not self.sizes:
            raise EvalVLMError(f"--sizes must be in 0..{train_classes} (the training "
                               f"classes), got {', '.join(map(str, self.sizes)) or 'none'}")
        if self.vlm.configured and not self.vlm.model:
            raise EvalVLMError("--url needs --model")


def draw_classes(train_classes: Sequence[str], size: int, seed: int, draw: int
                 ) -> tuple[str, ...]:
    """``size`` of the training classes, a seeded draw, kept in their original order."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, size, draw]))
    pick = sorted(rng.choice(len(train_classes), size, replace=False).tolist())
    return tuple(train_classes[i] for i in pick)


def draw_seed(seed: int, size: int, draw: int) -> int:
    """The training seed of one draw."""
    return int(np.random.SeedSequence([seed, size, draw, 1]).generate_state(1)[0] % 2**31)


def data_digest(presses: PressSet) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(presses.x).tobytes())
    h.update(np.ascontiguousarray(presses.x_bar).tobytes())
    h.update("\n".join(presses.labels).encode())
    return h.hexdigest()


@dataclass(frozen=True)
class Draw:
    size: int
    index: int
    classes: tuple[str, ...]
    directory: Path | None  # the training's run directory (None: vision only)
    seconds: float | None = None  # how long its training took (now or when cached)
    epochs: int | None = None
    trained_now: bool = False


def _trained(cfg: Fig6Config, presses: PressSet, splits: Splits, model_config: ModelConfig,
             digest: str, size: int, index: int, bars: Progress) -> tuple[Draw, Any, Any]:
    """One draw's encoder: loaded from its run directory when made for the same key, else
    trained now."""
    classes = draw_classes(splits.train, size, cfg.seed, index)
    seed = draw_seed(cfg.seed, size, index)
    run_dir = cfg.work / f"n{size:02d}_d{index}"
    key = {"format": RESULT_FORMAT, "classes": list(classes), "val": list(splits.val),
           "seed": seed, "model": model_config.to_dict(), "max_epochs": cfg.max_epochs,
           "patience": cfg.patience, "data": digest,
           # (the normaliser's floor changes what is trained as much as the model does)
           "std_floor": STD_FLOOR_FRACTION}
    result_path = run_dir / RESULT
    if result_path.exists() and (run_dir / CHECKPOINT).exists():
        try:
            saved = json.loads(result_path.read_text())
        except (OSError, ValueError):
            saved = {}
        if saved.get("key") == key:
            model, norm, _ = load_checkpoint(run_dir / CHECKPOINT)
            log.info("fig6 n=%d draw %d: trained before (%s), loaded", size, index, run_dir)
            return (Draw(size, index, classes, run_dir, saved.get("seconds"),
                         saved.get("epochs")), model, norm)
    sub = Splits(classes, splits.val, splits.descriptions)
    config = TrainConfig(model=model_config, seed=seed, max_epochs=cfg.max_epochs,
                         patience=cfg.patience, threads=cfg.threads)
    result = train(training_data_of(presses, sub), config, run_dir, bars)
    atomic_write_text(result_path, json.dumps(
        {"key": key, "epochs": result.epochs, "best_epoch": result.best_epoch,
         "best_val": result.best_val, "seconds": result.seconds}, indent=1) + "\n")
    return (Draw(size, index, classes, run_dir, result.seconds, result.epochs, True),
            result.model, result.norm)


def _cache_path(cfg: Fig6Config) -> Path:
    name = slug(cfg.vlm.model or "simulated-vlm")
    if cfg.standin:
        from edge.sim.standin_vlm import knowledge_digest

        name += f"@{knowledge_digest()[:12]}"
    return cfg.work / name / ANSWERS_FILE


def _window(model_dir: Path) -> tuple[WindowSpec, ModelConfig]:
    """The shipped model's window and model configuration (what the retrained encoders
    copy)."""
    manifest = read_manifest(model_dir)
    spec = manifest.get("encoder", {}).get("window")
    window = WindowSpec(**spec) if spec else DEFAULT_WINDOW
    model = manifest.get("training", {}).get("vq", {}).get("config", {}).get("model")
    return window, ModelConfig.from_dict(model) if model else ModelConfig()


async def run(cfg: Fig6Config, *, progress: bool = True) -> dict[str, Any]:
    """Train (or load) every draw's encoder, ask what is not cached, write the report."""
    started = time.perf_counter()
    window, shipped = await asyncio.to_thread(_window, cfg.model_dir)
    model_config = dataclasses.replace(shipped, decoder=cfg.decoder or shipped.decoder)
    presses, splits = await asyncio.to_thread(load_reference, cfg.reference, window)
    cfg.validate(len(splits.train))
    sets = await asyncio.to_thread(load_sets, cfg.unseen, cfg.limit, window)
    digest = await asyncio.to_thread(data_digest, presses)
    vision, method = CONDITIONS["vision_only"], CONDITIONS["vq_top3"]
    templates = {c.mode: load_template(c.mode, cfg.vlm.prompt_dir) for c in (vision, method)}
    images = ImageSource(cfg.images, cfg.vlm)
    model_name = cfg.vlm.model or "simulated-vlm"

    trainings = [(n, d) for n in cfg.sizes if n > 0 for d in range(cfg.draws)]
    bar = Bar("fig6 encoders", len(trainings), "trainings", enabled=progress)
    train_bars = Progress(enabled=progress)
    draws: list[Draw] = []
    jobs: dict[tuple[int, int], list[Job]] = {}
    for n in cfg.sizes:
        if n == 0:
            for d in range(cfg.draws):  # one set of questions: every draw shares its answers
                draws.append(Draw(0, d, (), None))
                jobs[(0, d)] = build_jobs(sets, [(vision, None)], templates, images,
                                          model_name)
            continue
        for d in range(cfg.draws):
            draw, model, norm = await asyncio.to_thread(
                _trained, cfg, presses, splits, model_config, digest, n, d, train_bars)
            draws.append(draw)
            chosen = presses.select(draw.classes)
            tactile = torch_tactile(
                "vq", model, norm, (chosen, Splits(draw.classes, (), splits.descriptions)))
            jobs[(n, d)] = await asyncio.to_thread(
                build_jobs, sets, [(method, tactile)], templates, images, model_name)
            bar.update(1, f"|Y_ref| {n} draw {d}"
                       + (f": {draw.seconds:.0f} s, {draw.epochs} epochs" if draw.trained_now
                          else ": cached"))
    bar.close()
    t_train = time.perf_counter() - started

    all_jobs = tuple(j for js in jobs.values() for j in js)
    ecfg = EvalVLMConfig(vlm=cfg.vlm, out=_cache_path(cfg).parent, unseen=cfg.unseen,
                         model_dir=cfg.model_dir, conditions=("vision_only", "vq_top3"),
                         limit=cfg.limit, concurrency=cfg.concurrency)
    cache = AnswerCache(_cache_path(cfg))
    await asyncio.to_thread(cache.load)
    keys = {j.key for j in all_jobs}
    eval_bar = EvalProgress(len(keys), len(keys & set(cache.records)),
                            enabled=progress)
    if cfg.standin:
        from edge.sim.standin_vlm import DEFAULT, server

        async with server() as srv:
            ecfg = dataclasses.replace(ecfg, vlm=dataclasses.replace(
                cfg.vlm, base_url=srv.base_url, model=DEFAULT.model))
            await _ask(ecfg, sets, templates, all_jobs, cache, eval_bar, images.name)
    else:
        await _ask(ecfg, sets, templates, all_jobs, cache, eval_bar, images.name)
    report = summarise(cfg, draws, jobs, cache.records, model_name, model_config,
                       t_train, time.perf_counter() - started)
    report["data"] = {
        "reference": {"directory": str(cfg.reference), "train_classes": len(splits.train),
                      "origin": reference_origin(cfg.reference)},
        "sets": [{"name": ts.name, "paper_set": paper_set(ts.name, cfg.paper_sets),
                  "origin": ts.origin} for ts in sets],
        "images": images.name}
    await asyncio.to_thread(write_report, cfg, report)
    return report


async def _ask(ecfg: EvalVLMConfig, sets, templates, jobs, cache, bar, images_name) -> None:
    plan = Plan(ecfg, tuple(sets), (CONDITIONS["vision_only"], CONDITIONS["vq_top3"]),
                templates, jobs, images_name)
    await ask_all(plan, cache, progress=bar)


def _accuracy(jobs: Sequence[Job], records: Mapping[str, Mapping[str, Any]], dataset: str
              ) -> dict[str, Any]:
    mine = [j for j in jobs if j.dataset == dataset]
    correct = sum(records[j.key]["answer"].get("status") == "ok"
                  and records[j.key]["answer"].get("label") == j.label for j in mine)
    return {"correct": int(correct), "n": len(mine),
            "accuracy": correct / len(mine) if mine else None}


def summarise(cfg: Fig6Config, draws: Sequence[Draw], jobs: Mapping[tuple[int, int], list[Job]],
              records: Mapping[str, Mapping[str, Any]], model: str,
              model_config: ModelConfig, train_s: float, total_s: float) -> dict[str, Any]:
    missing = [j.key for js in jobs.values() for j in js if j.key not in records]
    if missing:
        raise EvalVLMError(f"{len(missing)} answers missing (first: {missing[0]})")
    names = list(dict.fromkeys(j.dataset for js in jobs.values() for j in js))
    runs = []
    for draw in draws:
        js = jobs[(draw.size, draw.index)]
        runs.append({"size": draw.size, "draw": draw.index, "classes": list(draw.classes),
                     "run_dir": str(draw.directory) if draw.directory else None,
                     "train_seconds": draw.seconds, "epochs": draw.epochs,
                     "trained_now": draw.trained_now,
                     "results": {ds: _accuracy(js, records, ds) for ds in names}})
    sizes = []
    for n in cfg.sizes:
        row: dict[str, Any] = {"size": n, "sets": {}}
        for ds in names:
            accs = [r["results"][ds]["accuracy"] for r in runs if r["size"] == n]
            arr = np.asarray(accs, dtype=np.float64)
            row["sets"][ds] = {
                "values": accs, "mean": float(arr.mean()),
                "std": float(arr.std(ddof=1)) if len(arr) > 1 else 0.0,
                "paper": PAPER_ENDS.get(n, {}).get(
                    paper_set(ds, cfg.paper_sets) or "")}
        sizes.append(row)
    trained = [r["train_seconds"] for r in runs if r["train_seconds"] is not None]
    return {
        "title": "Fig. 6: accuracy against the number of reference classes"
                 + (" (simulated VLM)" if cfg.standin else ""),
        "simulated_vlm": cfg.standin, "model": model, "base_url": cfg.vlm.base_url,
        "decoder": model_config.decoder, "latent": model_config.latent,
        "metric": model_config.metric,
        "seed": cfg.seed, "draws": cfg.draws,
        "max_epochs": cfg.max_epochs, "patience": cfg.patience, "limit": cfg.limit,
        "protocol": "vision + tactile, top-3; |Y_ref| drawn from the training classes, "
                    "encoder retrained on them (validation classes for early stopping), "
                    "database of the drawn classes only (all offsets); |Y_ref| = 0 is "
                    "vision only; std over draws with ddof = 1",
        "sizes": sizes, "runs": runs,
        "timings": {"trainings": len(trained),
                    "trainings_run": sum(r["trained_now"] for r in runs),
                    "train_seconds_total": float(sum(trained)),
                    "train_seconds_mean": float(np.mean(trained)) if trained else None,
                    "train_phase_s": train_s, "total_s": total_s},
    }


def _pct(v: float | None) -> str:
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{100 * v:.1f}"


def _sets(r: Mapping[str, Any]) -> tuple[list[str], list[str]]:
    """The sets' names and titles (a set standing beside one of the paper's says which)."""
    names = list(r["sizes"][0]["sets"]) if r["sizes"] else []
    data = r.get("data", {})
    mapping = {d["name"]: d["paper_set"] for d in data.get("sets", []) if d.get("paper_set")}
    return names, [set_title(ds, mapping) for ds in names]


def markdown(r: Mapping[str, Any]) -> str:
    names, titles = _sets(r)
    lines = [f"# {r['title']}", ""]
    if r["simulated_vlm"]:
        lines += ["**Simulated VLM, not a real model** (`edge/sim/standin_vlm.py`: sight "
                  "plus common sense about object names; see `table1.md`). What moves here "
                  "is the encoder and the database: what a VLM is told the press felt "
                  "like.", ""]
    data = r.get("data", {})
    ref = data.get("reference", {})
    # (Reports written before these were recorded name the decoder only.)
    shape = (f"z of {r['latent']} numbers, metric term weight {r['metric']:g}, "
             if "latent" in r else "")
    lines += [f"VLM `{r['model']}`; encoders retrained per draw ({shape}decoder "
              f"`{r['decoder']}`: "
              f"{decoder_title(r['decoder'])}; at most {r['max_epochs']} epochs, "
              f"patience {r['patience']}); {r['draws']} draws per size, seed {r['seed']}. "
              f"{r['protocol']}.", "",
              f"Reference classes: `{ref.get('directory')}` ({ref.get('train_classes')} "
              f"training classes, {describe_origin(ref.get('origin'))}); test sets: "
              + "; ".join(f"{d['name']} ({describe_origin(d.get('origin'))})"
                          for d in data.get("sets", []))
              + f"; images: {data.get('images')}.", "",
              "| classes in Y_ref | " + " | ".join(f"{t} mean ± std (%)" for t in titles)
              + " | "
              + " | ".join(f"{t} per draw" for t in titles) + " | paper (GPT-4V) |",
              "| --- |" + " --- |" * (2 * len(names) + 1)]
    for row in r["sizes"]:
        cells = [f"{_pct(row['sets'][ds]['mean'])} ± {_pct(row['sets'][ds]['std'])}"
                 for ds in names]
        per = [" ".join(_pct(v) for v in row["sets"][ds]["values"]) for ds in names]
        paper = ", ".join(f"{t} {row['sets'][ds]['paper']:.1f}" for t, ds in
                          zip(titles, names, strict=True)
                          if row["sets"][ds]["paper"] is not None)
        lines.append(f"| {row['size']} | " + " | ".join(cells) + " | " + " | ".join(per)
                     + f" | {paper} |")
    t = r["timings"]
    lines += ["", "The paper reports these two end points (its Table I) and, between them, "
              "no clear trend, the full set best."]
    if t["trainings"]:
        lines[-1] += (f" The {t['trainings']} encoders took {t['train_seconds_total']:.0f} s "
                      f"to train ({t['train_seconds_mean']:.0f} s each on average, when each "
                      f"was trained); this run trained {t['trainings_run']} of them and took "
                      f"{t['total_s']:.0f} s in all.")
    lines += ["Per-draw classes, epochs and training times: `fig6.json`.", ""]
    return "\n".join(lines)


def plot(r: Mapping[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    names, titles = _sets(r)
    for i, (ds, title) in enumerate(zip(names, titles, strict=True)):
        xs = [row["size"] for row in r["sizes"]]
        mean = [100 * row["sets"][ds]["mean"] for row in r["sizes"]]
        std = [100 * row["sets"][ds]["std"] for row in r["sizes"]]
        ax.errorbar(xs, mean, yerr=std, marker="o", capsize=3, color=f"C{i}",
                    label=f"{title} ({r['model']})")
        ends = [(row["size"], row["sets"][ds]["paper"]) for row in r["sizes"]
                if row["sets"][ds]["paper"] is not None]
        if ends:
            ax.scatter([n for n, _ in ends], [v for _, v in ends], marker="s",
                       facecolors="none", edgecolors=f"C{i}", label=f"{title}, paper (GPT-4V)")
    ax.set_xlabel("|Y_ref| (reference classes)")
    ax.set_ylabel("accuracy (%)")
    ax.set_xticks([row["size"] for row in r["sizes"]])
    ax.set_ylim(0, 100)
    ax.set_title(r["title"], fontsize=8)
    ax.legend(fontsize=6, loc="lower right")
    fig.tight_layout()
    save_png(fig, path, DPI)
    plt.close(fig)


def write_report(cfg: Fig6Config, report: Mapping[str, Any]) -> None:
    cfg.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(cfg.out / REPORT_JSON, json.dumps(report, indent=1) + "\n")
    atomic_write_text(cfg.out / REPORT_MD, markdown(report))
    plot(report, cfg.out / REPORT_PNG)
    log.info("Fig. 6 written to %s", cfg.out / REPORT_MD)
