"""``reradar fit-confidence``: fit the shipped confidence model on training splits (one command to re-fit)."""

from __future__ import annotations

import hashlib
import json
import shlex
import sys
from pathlib import Path

import typer

from reradar_core.errors import ConfigError, ReRadarError


def _spacings(text: str) -> tuple[float, ...]:
    """``--map-spacings-m``: distinct finite spacings >= 0 (metres), in the given order."""
    out: list[float] = []
    for item in (t.strip() for t in text.split(",")):
        try:
            value = float(item)
        except ValueError:
            raise ConfigError(f"--map-spacings-m: {item!r} is not a number of metres") from None
        if not (value >= 0.0 and value < 1e4):
            raise ConfigError(f"--map-spacings-m: {item!r} must be between 0 and 10000 m")
        if value not in out:
            out.append(value)
    return tuple(out)


def register(app: typer.Typer) -> None:
    @app.command("fit-confidence")
    def fit_confidence(
        splits: str = typer.Option("train-target-boreas,train-target-loop,train-target-loop-open,train-target-offroad",
                                   help="Comma-separated training splits (never benchmark query sequences)."),
        query_step: int = typer.Option(1, min=1, help="Use every N-th query scan of each split."),
        holdout: float = typer.Option(0.15, min=0.05, max=0.5,
                                      help="Tail fraction of each query sequence held out for the reliability "
                                           "numbers (the descriptor's validation tail)."),
        l2: float = typer.Option(1.0, min=0.0, help="L2 penalty on the standardised weights."),
        max_wrong_pct: float = typer.Option(0.5, min=0.0, max=100.0,
                                            help="The bar is at least the lowest confidence at which wrong "
                                                 "localized answers are at most this percent of the fit runs "
                                                 "of every group: each split's training, unseen and look-alike "
                                                 "sessions (and map spacing)."),
        wrong_cost: float = typer.Option(10.0, min=0.0,
                                         help="The bar also minimises WRONG_COST x wrong answers + refused correct "
                                              "answers on the fit runs (0: only the --max-wrong-pct rule)."),
        out: Path = typer.Option(None, help="Model JSON (default: the shipped "
                                            "reradar_core/localization/confidence_model.json)."),
        plot: Path = typer.Option(None, help="Reliability diagram (.png, .pdf or .svg; default: with the default "
                                             "--out the checkout's docs/img/confidence_reliability.png, else "
                                             "<out>.png beside the model JSON)."),
        models: str = typer.Option("", help="Comma-separated SPLIT=MODEL: judge these models' answers instead of "
                                            "each split's target-adapted one (e.g. "
                                            "train-target-boreas=our-3-boreas-w05)."),
        map_spacings_m: str = typer.Option("0", help="Comma-separated keyframe spacings (metres, as "
                                                     "`reradar build-map --min-spacing-m`) of the maps the "
                                                     "queries are localized on; 0 = every scan of the "
                                                     "domain's map drive (3.8-6.7 m apart). Each spacing's "
                                                     "runs are a group of their own for the bar."),
        lookalike: bool = typer.Option(True, help="Also localize each split's confidence sessions driven in a "
                                                  "look-alike world (the map's roads, other surroundings: every "
                                                  "localized answer is wrong; `reradar sim-suite "
                                                  "train-target-X-lookalike`), a group of their own for the bar."),
        periodic: bool = typer.Option(True, help="Also localize each split's confidence sessions in a periodic "
                                                 "world (the map's roads with one 40 m tile layout everywhere, so a "
                                                 "street repeats itself; the map drive rendered there too; `reradar "
                                                 "sim-suite train-target-X-periodic`): they choose the tie margin "
                                                 "(LocalizationConfig.min_place_margin, reported as place_margin), "
                                                 "not the coefficients, floor or bar."),
        reuse: bool = typer.Option(False, help="Re-fit from the runs saved by the last collection with the same "
                                               "splits, step, models, spacings, --lookalike and --periodic (cache) "
                                               "instead of "
                                               "localizing again; an error when there are none."),
        progress: bool = typer.Option(True, help="Progress bars."),
        threads: int = typer.Option(1, min=1, help="Torch threads (the machine is shared)."),
    ) -> None:
        """Localize training-split queries, fit the confidence model and the aligned-landmark floor, write its JSON
        and a reliability diagram."""
        import torch

        from reradar_core.localization.confidence import DEFAULT_MODEL_PATH
        from reradar_core.localization.confidence_fit import (
            PROBE_FLOOR,
            FitData,
            collect_split,
            fit_from_data,
            plot_reliability,
            split_models,
        )
        from reradar_core.paths import cache_dir, output_file
        from reradar_core.sim.writer import SIM_VERSION

        torch.set_num_threads(threads)
        names = [s.strip() for s in splits.split(",") if s.strip()]
        try:
            # both outputs are checked before the hour of localization, and written only when both can be
            target = output_file(out or DEFAULT_MODEL_PATH, "--out", (".json",))
            if plot is None:
                docs_img = DEFAULT_MODEL_PATH.parents[2] / "docs" / "img"  # a checkout, not an installed package
                plot = (docs_img / "confidence_reliability.png" if out is None and docs_img.is_dir()
                        else target.with_suffix(".png"))
            plot = output_file(plot, "--plot", (".png", ".pdf", ".svg"))
            split_model = split_models(models, names)
            spacings = _spacings(map_spacings_m)
            # the runs are cached per set of judged models (a model change never re-uses another model's runs)
            tag = "-models-" + hashlib.sha256(json.dumps(split_model, sort_keys=True).encode()).hexdigest()[:12]
            maps_tag = "" if spacings == (0.0,) else "-maps-" + "+".join(f"{m:g}m" for m in spacings)
            look_tag = ("-lookalike" if lookalike else "") + ("-periodic" if periodic else "")
            runs_path = cache_dir("confidence") / (f"runs-v{SIM_VERSION}-{'+'.join(names)}-step{query_step}"
                                                 f"-floor{PROBE_FLOOR:.2f}-with-unseen{tag}{maps_tag}{look_tag}.npz")
            if reuse and not runs_path.is_file():
                raise ConfigError("--reuse: no saved runs for these splits, step, models, map spacings, "
                                  f"--lookalike and --periodic ({runs_path.name} is not in the cache; runs "
                                  "collected without look-alike sessions need --no-lookalike, without periodic "
                                  "worlds --no-periodic); run without --reuse to collect them")
            if reuse:
                data = FitData.load(runs_path)
            else:
                data = FitData.concat([collect_split(s, query_step, holdout, progress, model=split_model[s],
                                                     map_spacing_m=m, lookalike=lookalike, periodic=periodic)
                                       for s in names for m in spacings])
                data.save(runs_path)
            meta = {"command": "reradar " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
                    "splits": names, "sim_version": SIM_VERSION, "query_step": query_step, "holdout": holdout,
                    "map_spacings_m": list(spacings), "lookalike": lookalike, "periodic": periodic,
                    "runs_from_cache": reuse,
                    "l2": l2, "label": "pose within the suite's success thresholds (e_t < R, e_r < 10 deg)"}
            meta["models"] = split_model
            model, report = fit_from_data(data, l2, max_wrong_pct / 100.0, meta, wrong_cost or None)
        except ReRadarError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from exc
        own = data.has_pose & ~data.periodic  # the periodic worlds' runs choose the tie margin, not the model
        ho = own & data.heldout
        fit = own & ~data.heldout
        unseen = own & data.unseen
        plot_reliability({"held-out runs": (model.predict(data.cues[ho]), data.correct[ho]),
                          "fit runs": (model.predict(data.cues[fit]), data.correct[fit]),
                          "unseen sessions (all)": (model.predict(data.cues[unseen]), data.correct[unseen])}, plot,
                         f"answer confidence on training splits\n{', '.join(names)}\nheld-out ECE "
                         f"{report['ece_heldout']:.3f} (10 bins)", bar=model.min_confidence)
        model.save(target)  # after the plot: a failed plot leaves the earlier model in place
        typer.echo(f"wrote {target} and {plot}", err=True)
        typer.echo(json.dumps({"model": target.name, "coef": dict(zip(model.cue_names, model.coef.round(3).tolist(),
                                                                       strict=True)),
                               **report}, indent=2))
