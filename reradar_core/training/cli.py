"""``reradar train``: InfoNCE training of the descriptor network on simulated (or real) sequences."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import re
import shlex
import sys
import time
from pathlib import Path

import typer

from reradar_core.errors import ConfigError, ReRadarError
from reradar_core.training.suites import SeqSpec

__all__ = ["TrainingInterrupted", "register", "train_main"]

logger = logging.getLogger(__name__)


def _cached(spec: SeqSpec, width_px: int, resolution_m: float, progress: bool):
    """A sequence folder, or an already rendered Cartesian cache folder (images.npy + poses.npy)."""
    import numpy as np

    from reradar_core.io.datasets import load_sequence
    from reradar_core.training.data import CachedSequence, cache_sequence

    if (spec.path / "images.npy").is_file() and (spec.path / "poses.npy").is_file():
        seq = CachedSequence(spec.path.name, spec.group, np.load(spec.path / "images.npy", mmap_mode="r"),
                             np.load(spec.path / "poses.npy"), resolution_m)
        return seq.fraction(spec.start, spec.stop)
    seq = cache_sequence(load_sequence(spec.path, preset=spec.preset, pose_time_unit=spec.time_unit), width_px,
                         resolution_m, group=spec.group, progress=progress)
    return seq.fraction(spec.start, spec.stop)


#: A model name is a plain file stem: it names ``<out-dir>/<name>.pt`` and must not lead out of the folder.
_MODEL_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]*")


def _model_name(value: str) -> str:
    if not _MODEL_NAME.fullmatch(value):
        raise typer.BadParameter(f"{value!r} is not a plain file name: use letters, digits, '-', '_' and '.', "
                                 "not starting with '.' (no folders: --out-dir chooses the folder)")
    return value


def _finite_non_negative(value: float) -> float:
    if not (math.isfinite(value) and value >= 0):
        raise typer.BadParameter(f"must be a finite number >= 0, got {value}")
    return value


def _place_group(folder: Path, shared_frame: bool) -> str:
    """Place group of a ``--sequence`` folder: one for all of them with ``--shared-frame``; else the simulated world
    it was rendered in (the drives of one suite share its world frame: ``suite`` and ``world_seed`` of its
    ``reradar_sim.json``), else the folder itself (a recorded drive's poses are compared only with its own)."""
    if shared_frame:
        return "shared-frame"
    try:
        meta = json.loads((folder / "reradar_sim.json").read_text())
        if isinstance(meta, dict) and meta.get("suite") and meta.get("world_seed") is not None:
            return f"sim:{meta['suite']}:{meta['world_seed']}"
    except (OSError, ValueError):
        pass
    return f"seq:{folder.resolve()}"


def _refuse_options_the_init_model_fixes(init: str, **given: float | None) -> None:
    """``--width`` / ``--clusters`` / ``--dim`` given with ``--init`` must be the init model's own (its weights fix
    them; they were silently ignored): a different value is refused, naming it."""
    from reradar_core.model.registry import resolve_weights

    _, meta = resolve_weights(init)
    cfg = meta.get("config", {})
    actual = {"width": cfg.get("width"), "clusters": cfg.get("num_clusters"), "dim": cfg.get("output_dim") or 0}
    wrong = [f"--{k} {v:g} (the model's: {actual[k]})" for k, v in given.items()
             if v is not None and actual[k] is not None and float(v) != float(actual[k])]
    if wrong:
        raise typer.BadParameter(f"--init {init} fixes the network's shape, so {', '.join(wrong)} cannot apply; "
                                 "leave these options out (or train from scratch without --init)")


def _positive_finite(value: float | None) -> float | None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise typer.BadParameter(f"must be a positive number, got {value}")
    return value


def _command_line() -> str:
    """This process's command line, with the console script named as a user types it (``reradar ...``)."""
    argv = list(sys.argv)
    # ``reradar ...`` and ``python -m reradar_cli ...`` (argv[0] = .../reradar_cli/__main__.py) are the same
    # command; never record the install path
    if argv and (Path(argv[0]).name == "reradar" or Path(argv[0]).parent.name == "reradar_cli"):
        argv[0] = "reradar"
    return " ".join(shlex.quote(a) for a in argv)


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C during ``train_main``; ``str()`` says where the run stands and how to resume it."""


def train_main(name: str, sequences: list[SeqSpec], val_pairs: list[tuple[SeqSpec, SeqSpec]], *,
               backbone: str = "reresnet",
               width: float = 0.25, clusters: int = 32, dim: int | None = 256, init: str | None = None,
               lr: float | None = None, steps: int = 1500, minutes: float = 60.0, seed: int = 0,
               threads: int = 1, device: str = "auto", out_dir: Path | None = None, run_dir: Path | None = None,
               resume: bool = True,
               data_note: str = "", progress: bool = True, command: str | None = None, disc_mask: bool = True,
               summary_out: dict | None = None, **train_kwargs) -> Path | None:
    """Train (or adapt, with ``init``) a model and write ``<out_dir>/<name>.pt`` + ``.json``; returns the path.

    ``steps=0`` only validates (the ``init`` model, or a fresh one after its head initialisation): it neither
    resumes nor writes anything (no weights, no checkpoint), puts the summary in ``summary_out`` and returns None.
    """

    from reradar_core.model.config import ModelConfig
    from reradar_core.model.extractor import read_weights_blob
    from reradar_core.model.registry import WEIGHTS_DIR, resolve_weights, save_weights
    from reradar_core.paths import cache_dir
    from reradar_core.training.trainer import TrainConfig, Trainer, resolve_device, trainable_state

    resolve_device(device)  # an unknown device or no CUDA: said before a run folder is made (it was left empty)
    init_state = None
    if init is not None:
        pt, meta = resolve_weights(init)
        try:
            blob, _ = read_weights_blob(pt, meta)
        except ConfigError as exc:
            raise ConfigError(f"--init {init}: {exc}") from None
        # the disc mask has no parameters: it follows the flag whatever the init model was trained with
        model = dataclasses.replace(ModelConfig.from_dict(meta["config"]), disc_mask=disc_mask)
        # the plain ResNet trains as it runs; the ReResNet needs its e2cnn (basis-coefficient) state
        init_state = blob.get("train_state_dict") or (blob["state_dict"] if model.backbone == "resnet" else None)
        if init_state is None:
            raise ConfigError(f"{pt} has no training state; it cannot initialise `reradar train --init`")
        if model.backbone != backbone:
            raise ConfigError(f"--init {init} is a {model.backbone} model but --backbone is {backbone}")
    else:
        model = ModelConfig(backbone=backbone, width=width, num_clusters=clusters, output_dim=dim,
                            disc_mask=disc_mask)
    if lr is None:
        lr = 1e-5 if init is not None else 1e-4  # paper: 1e-4 from scratch, 1e-5 when adapting
    cfg = TrainConfig(model=model, lr=lr, max_steps=steps, max_minutes=minutes, seed=seed, num_threads=threads,
                      device=device, **train_kwargs)
    t0 = time.monotonic()
    w = model.cartesian_width_px
    res = model.cartesian_resolution_m
    train = [_cached(s, w, res, progress) for s in sequences]
    vals = [(_cached(a, w, res, progress), _cached(b, w, res, progress)) for a, b in val_pairs]
    cache_s = time.monotonic() - t0
    if steps == 0:  # validation only: no checkpoint to resume or write, no weights
        trainer = Trainer(cfg, train, vals, run_dir=None, init_state=init_state, progress=progress)
        _, summary = trainer.run(resume=False)
        logger.info("validation only (--steps 0): val Recall@1 %s, raw NetVLAD %s, %s queries; nothing written",
                    summary.get("val_recall_at_1"), summary.get("val_recall_at_1_raw_netvlad"),
                    summary.get("val_queries"))
        if summary_out is not None:
            summary_out.update(summary)
        return None
    run_dir = run_dir or cache_dir("training", "runs", name)
    trainer = Trainer(cfg, train, vals, run_dir=run_dir, init_state=init_state, progress=progress)
    try:
        plain, summary = trainer.run(resume=resume)
    except KeyboardInterrupt:
        last = trainer.checkpoint_step
        where = (f"the last checkpoint ({trainer.checkpoint_path}) is at step {last}: the same command resumes "
                 "from it" if last is not None else
                 f"no checkpoint was written yet (one every {cfg.checkpoint_every} steps): the same command starts "
                 "over")
        raise TrainingInterrupted(f"interrupted at step {trainer.step}; {where}") from None
    out = (out_dir or WEIGHTS_DIR) / f"{name}.pt"

    def _desc(s: SeqSpec) -> str:
        part = "" if (s.start, s.stop) == (0.0, 1.0) else f" [{s.start:.2f}, {s.stop:.2f})"
        folder = s.path.resolve()  # a relative --sequence names its parent too (not "/db")
        return f"{folder.parent.name}/{folder.name}{part}"

    meta = {
        "description": data_note,
        "training_data": {"sequences": [_desc(s) for s in sequences], "num_scans": sum(len(s) for s in train),
                          "validation": [[_desc(a), _desc(b)] for a, b in val_pairs]},
        "init": init,
        "command": command if command is not None else _command_line(),
        "cache_time_s": round(cache_s, 1),
        "torch_threads": threads,
        "device": str(trainer.device),
        **summary,
    }
    train_state = trainable_state(trainer.net) if model.backbone == "reresnet" else None
    path = save_weights(plain, out, meta, train_state_dict=train_state)
    logger.info("wrote %s (val Recall@1 %s)", path, summary.get("val_recall_at_1"))
    return path


def register(app: typer.Typer) -> None:
    @app.command("train")
    def train_cmd(
        name: str = typer.Option(..., callback=_model_name, help="Model name (letters, digits, -, _, .): writes "
                                 "<out-dir>/<name>.pt and .json; its checkpoints live in the cache "
                                 "(<cache>/training/runs/<name>, whatever --out-dir), so a run of the same name "
                                 "resumes there: give another name (or --no-resume) for an unrelated run."),
        split: str | None = typer.Option(None, help="Simulated training split: train-source, "
                                         "train-target-boreas|loop|loop-open|offroad, smoke (see docs/MODEL.md); "
                                         "several, comma-separated, train on all of them (same recall radius)."),
        sequence: list[Path] = typer.Option([], "--sequence", help="Training sequence folder (repeatable)."),
        val_db: Path | None = typer.Option(None, help="Validation database sequence folder."),
        val_query: Path | None = typer.Option(None, help="Validation query sequence folder."),
        backbone: str = typer.Option("reresnet", help="reresnet (C8, e2cnn) or resnet (ablation)."),
        width: float | None = typer.Option(None, help="Width multiplier on ResNet-50 channel counts (default "
                                           "0.25; with --init, the init model's)."),
        clusters: int | None = typer.Option(None, help="NetVLAD clusters K (default 32; with --init, the init "
                                            "model's)."),
        dim: int | None = typer.Option(None, min=0, help="PCA-whitening output dimension D, 0 = raw NetVLAD "
                                       "(default 256; with --init, the init model's)."),
        init: str | None = typer.Option(None, help="Adapt from this shipped model (name or .pt path)."),
        lr: float | None = typer.Option(None, callback=_positive_finite,
                                        help="AdamW learning rate (default 1e-4, 1e-5 with --init)."),
        steps: int = typer.Option(1500, min=0, help="Maximum optimisation steps (0: only validate the model, "
                           "write nothing)."),
        minutes: float = typer.Option(60.0, callback=_positive_finite, help="Wall-clock budget in minutes."),
        seed: int = typer.Option(0, min=0, max=2**63 - 1, help="Random seed (sampling, augmentation, "
                                 "initialisation)."),
        threads: int = typer.Option(1, min=1, help="torch CPU threads (1 is fastest on a busy shared CPU)."),
        device: str = typer.Option("auto", help="auto (CUDA GPU when available, else CPU), cpu or cuda."),
        out_dir: Path | None = typer.Option(None, help="Where to write the weights (default: the package)."),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing <out-dir>/<name>.pt (e.g. "
                                       "retraining a shipped model: scripts/train_models.sh passes it)."),
        no_resume: bool = typer.Option(False, "--no-resume", help="Ignore an existing checkpoint."),
        hard_negatives: int = typer.Option(0, help="Negatives per query (of 14, even) mined from a memory bank "
                                           "of global descriptors instead of drawn at random (0 = off)."),
        hard_refresh: int = typer.Option(100, help="Refresh the hard-negative memory bank every K steps."),
        learned_whitening: bool = typer.Option(False, "--learned-whitening", help="After the last step, replace "
                                               "the projection by learned whitening from matching pairs of the "
                                               "training scans (other traversals within 10 m, turned copies); "
                                               "docs/MODEL.md, 'Learned whitening'."),
        rotation_consistency: float = typer.Option(0.0, "--rotation-consistency", callback=_finite_non_negative,
                                                   help="Weight of a "
                                                   "rotation-consistency term: each anchor is seen again under "
                                                   "another heading and 1 - cosine of the two descriptors is "
                                                   "added to the loss (0 = off; docs/MODEL.md, 'Rotation "
                                                   "consistency')."),
        shared_frame: bool = typer.Option(False, "--shared-frame", help="The --sequence folders' poses share one "
                                          "map frame (drives of one route, e.g. GNSS poses): scans of different "
                                          "folders within 10 m are positives, within 25 m never negatives. Without "
                                          "it, folders rendered on one simulated route share their world; any "
                                          "other folder is compared only with itself."),
        preset: str | None = typer.Option(None, "--preset", help="Radar preset of the --sequence / --val-db / "
                                          "--val-query folders (boreas, boreas-2021, oxford, oord, mulran): a "
                                          "recorded Boreas folder must name it; simulated folders carry their own."),
        time_unit: str | None = typer.Option(None, "--time-unit", help="Unit of those folders' pose-file "
                                             "timestamps (s, ms, us, ns) when they are not absolute UTC times; "
                                             "never guessed."),
        no_disc_mask: bool = typer.Option(False, "--no-disc-mask", help="NetVLAD over all F' cells, not only "
                                          "the sensor disc (ModelConfig.disc_mask; the behaviour before it)."),
    ) -> None:
        """Train the descriptor network with InfoNCE (tau 0.1, 14 negatives) and save shipped weights."""
        seqs = [SeqSpec(p, _place_group(p, shared_frame), preset=preset, time_unit=time_unit) for p in sequence]
        vals: list[tuple[SeqSpec, SeqSpec]] = []
        note = ""
        summary: dict = {}  # --steps 0: the validation
        extra: dict = {"hard_negatives": hard_negatives, "hard_refresh_every": hard_refresh,
                       "learned_whitening": learned_whitening, "rotation_consistency": rotation_consistency}
        try:
            from reradar_core.model.registry import WEIGHTS_DIR
            from reradar_core.paths import output_dir

            # checked, not created: the folder is made when the weights are written (a refused or
            # validation-only run leaves no empty folder behind)
            target = output_dir(out_dir or WEIGHTS_DIR, "--out-dir", create=False) / f"{name}.pt"
            if target.exists() and not overwrite:  # before any work: a finished run must not end in a refusal
                raise typer.BadParameter(f"{target} exists; pass --overwrite to replace it, or choose another "
                                         "--name / --out-dir", param_hint="--name")
            if (preset or time_unit) and not (sequence or val_db):  # a split's renders carry their own
                given = [o for o, v in (("--preset", preset), ("--time-unit", time_unit)) if v]
                raise typer.BadParameter(f"{' and '.join(given)} appl{'y' if len(given) > 1 else 'ies'} to "
                                         "--sequence / --val-db / --val-query folders; a --split's renders carry "
                                         "their own")
            if preset is not None:
                from reradar_core.io.presets import get_preset

                get_preset(preset)  # an unknown name is refused before any work
            if (val_db is None) != (val_query is None):
                raise typer.BadParameter("--val-db and --val-query go together (a validation database and its "
                                         "queries)")
            if split is not None:
                from reradar_core.training.suites import suite_training_data

                names = [s.strip() for s in split.split(",") if s.strip()]
                repeated = sorted({n for n in names if names.count(n) > 1})
                if repeated:  # its scans would be trained on twice and its validation counted twice
                    raise typer.BadParameter(f"--split names {', '.join(repeated)} more than once")
                plans = [suite_training_data(n) for n in names]
                if not plans:
                    raise typer.BadParameter(f"--split {split!r} names no split")
                if len({p.radius_m for p in plans}) > 1:
                    raise typer.BadParameter(f"splits {split!r} have different recall radii; train them separately")
                for plan in plans:
                    seqs += plan.train
                    vals += plan.val
                note = "; ".join(p.note for p in plans)
                extra["recall_radius_m"] = plans[0].radius_m
            if val_db is not None and val_query is not None:
                vals.append((SeqSpec(val_db, "val", preset=preset, time_unit=time_unit),
                             SeqSpec(val_query, "val", preset=preset, time_unit=time_unit)))
            if not seqs:
                raise typer.BadParameter("give --split or at least one --sequence")
            if init is not None:
                _refuse_options_the_init_model_fixes(init, width=width, clusters=clusters, dim=dim)
            path = train_main(name, seqs, vals, backbone=backbone, width=0.25 if width is None else width,
                              clusters=32 if clusters is None else clusters,
                              dim=256 if dim is None else (dim or None),  # --dim 0: raw NetVLAD
                              init=init, lr=lr, steps=steps, minutes=minutes, seed=seed,
                              threads=threads, device=device, out_dir=out_dir, run_dir=None, resume=not no_resume,
                              data_note=note, disc_mask=not no_disc_mask, summary_out=summary, **extra)
        except ReRadarError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from exc
        except KeyboardInterrupt as exc:
            msg = str(exc) if isinstance(exc, TrainingInterrupted) else ("interrupted before training started; "
                                                                         "nothing written")
            typer.echo(f"\n{msg}", err=True)
            raise typer.Exit(130) from None
        if path is None:
            s = summary
            typer.echo(f"validation only (--steps 0): val Recall@1 {s.get('val_recall_at_1')}, raw NetVLAD "
                       f"{s.get('val_recall_at_1_raw_netvlad')} ({s.get('val_queries')} queries); nothing written")
            return
        meta = json.loads(path.with_suffix(".json").read_text())
        typer.echo(f"wrote {path} ({meta['model_id']}, {meta['steps']} steps, {meta['train_time_s']} s, "
                   f"val Recall@1 {meta.get('val_recall_at_1')})")
        if steps > 0 and not meta["steps"]:
            typer.echo("error: the run ended before its first optimisation step (the --minutes budget was spent "
                       "preparing the data?): these weights are untrained", err=True)
            raise typer.Exit(1)
