"""``reradar build-map``, ``map-info`` and ``map-repetition``: build, inspect and complete HDF5 keyframe maps."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import typer

from reradar_core.errors import ReRadarError

__all__ = ["register"]


def build_map_command(
    dataset: Path = typer.Option(..., "--dataset", help="Sequence folder (boreas, oxford or mulran layout)."),
    out: Path = typer.Option(..., "--out", help="Map file to write (.h5)."),
    layout: str | None = typer.Option(None, help="Dataset layout; detected when omitted."),
    preset: str | None = typer.Option(None, help="Radar preset; when omitted, a render's own or the layout's "
                                      "(Oxford, MulRan); a Boreas folder must name it (boreas or boreas-2021)."),
    time_unit: str | None = typer.Option(None, "--time-unit", help="Unit of the pose file's timestamps (s, ms, "
                                         "us, ns) when they are not absolute UTC times; never guessed."),
    batch_size: int = typer.Option(8, min=1, help="Scans per network batch."),
    min_spacing_m: float = typer.Option(0.0, min=0.0, help="Keep a scan as keyframe only this far (m) from the last. "
                                        "The answer confidence is fitted on maps with keyframes 3.8-6.7 m apart; "
                                        "at 12 m it refuses about 1 in 70 more revisits (docs/MODEL.md, "
                                        "'Sparser maps')."),
    max_keypoints: int | None = typer.Option(None, min=2, help="Cap stored keypoints per keyframe."),
    name: str | None = typer.Option(None, help="Map name stored in the file (default: sequence name)."),
    overwrite: bool = typer.Option(False, help="Replace an existing map file, and an existing <out>.far.h5 (rebuilt "
                                   "with --far-view, else removed: it would describe another map). Without it "
                                   "either is refused."),
    place_repetition: bool = typer.Option(True, "--place-repetition/--no-place-repetition",
                                          help="Measure where the map repeats itself (each keyframe localized "
                                          "against the map, ~20-40 ms per keyframe and thread) and store it, so no "
                                          "query pays for it (docs/MODEL.md, 'Repeated places')."),
    pose_clock_check: bool = typer.Option(True, "--pose-clock-check/--no-pose-clock-check",
                                          help="Check that the pose file runs on the scans' clock: every keyframe "
                                          "registered against the one before (5-25 ms a pair) and its turn compared "
                                          "with the poses'; a pose file more than a sweep off (GPS against UTC time: "
                                          "18 s) is refused, saying by how much (docs/MODEL.md, 'The pose clock')."),
    threads: int = typer.Option(1, min=1, help="torch CPU threads."),
    model: str = typer.Option("default", help="Descriptor model: registry name or .pt weights path."),
    far_view: bool = typer.Option(False, "--far-view/--no-far-view",
                                  help="Also write <out>.far.h5: the keyframes in ReRadar's far view (257 px at "
                                  "1.28 m/px, the radar's whole range), which the service uses for the answers the "
                                  "map's own view refuses (open land; docs/MODEL.md, 'The far view'). About twice "
                                  "the build time and map size."),
) -> None:
    """Build a keyframe map (global + local descriptors, poses) from a radar sequence folder."""
    import torch

    from maps.build import build_map_from_sequence
    from maps.store import read_metadata
    from reradar_core.io.poses import TIME_UNITS
    from reradar_core.localization.extractor import load_default_extractor
    from reradar_core.paths import output_file

    torch.set_num_threads(threads)
    if out.is_dir():
        typer.echo(f"error: {out} is a folder; --out names the map file to write (e.g. {out / 'map.h5'})", err=True)
        raise typer.Exit(2)
    if out.exists() and not overwrite:
        typer.echo(f"error: {out} exists; pass --overwrite to replace it", err=True)
        raise typer.Exit(2)
    from maps.paths import FAR_VIEW_SUFFIX, far_view_path

    if out.name.endswith(FAR_VIEW_SUFFIX):  # the service would take the map for a companion and never serve it
        typer.echo(f"error: --out {out.name}: a map's file name must not end in {FAR_VIEW_SUFFIX}, the name of a "
                   f"far-view companion (e.g. --out {out.name[: -len(FAR_VIEW_SUFFIX)]}.h5)", err=True)
        raise typer.Exit(2)
    companion = far_view_path(out)
    if (companion.exists() or companion.is_symlink()) and not overwrite:
        if far_view:
            typer.echo(f"error: {companion} exists; pass --overwrite to replace it", err=True)
        else:  # an earlier map's companion, found beside this map by the service; removed only when asked
            typer.echo(f"error: {companion} exists: the far-view companion of an earlier map, which would not "
                       f"describe this one; pass --overwrite to remove it (or --far-view --overwrite to rebuild it "
                       "with this map)", err=True)
        raise typer.Exit(2)
    try:
        if time_unit is not None and time_unit.strip().lower() not in TIME_UNITS:
            raise typer.BadParameter(f"--time-unit must be one of {sorted(TIME_UNITS)}, got {time_unit!r}")
        output_file(out, "--out", (".h5", ".hdf5"))  # before the network runs over the whole sequence
        extractor = load_default_extractor(model)
        kwargs: dict[str, object] = dict(batch_size=batch_size, max_keypoints=max_keypoints,
                                         overwrite=overwrite, show_progress=True, place_repetition=place_repetition)
        if name:
            kwargs["name"] = name
        if not pose_clock_check:
            kwargs["pose_clock"] = None
        if far_view:
            from reradar_core.localization import FarViewConfig

            kwargs["far_view"] = FarViewConfig()
        build_map_from_sequence(dataset, out, extractor, layout=layout, preset=preset,
                                min_spacing_m=min_spacing_m, time_unit=time_unit, **kwargs)
    except ReRadarError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    meta = read_metadata(out)
    typer.echo(f"wrote {out}: {meta.num_keyframes} keyframes, D={meta.descriptor_dim}, "
               f"model {meta.model_id}, {out.stat().st_size / 1e6:.1f} MB"
               + ("" if place_repetition else "; no place repetition stored (measured as keyframes first win)"))
    if far_view:
        far = far_view_path(out)
        typer.echo(f"wrote {far}: the same keyframes in the far view with their dense images, {far.stat().st_size / 1e6:.1f} MB")


def map_info_command(path: Path = typer.Argument(..., help="Map file (.h5).")) -> None:
    """Print a map's metadata as JSON, after checking that its arrays agree with it (poses, timestamps, global
    descriptors and keyframe groups, one per keyframe; the checks of opening a map for localization), and its stored
    place repetition (null when it has none): whether the default settings use it, the keyframes it marks
    (repetition >= LocalizationConfig.max_place_repetition), those it cannot judge (no keyframe of their own place
    aligns with them) and the largest repetition; how many keyframes have a known motion on the map drive
    (``keyframe_motion``: answers on the others are not motion-compensated); and, for a far-view companion, its
    keyframes' dense images (``dense_images``: null without them; ``default_settings``: this version correlates with
    them)."""
    from maps.store import open_map

    if path.is_dir():
        typer.echo(f"error: {path} is a folder, not a map file (.h5)", err=True)
        raise typer.Exit(2)
    from maps.build import motion_warning
    from reradar_core.localization import LocalizationConfig, repetition_settings
    from reradar_core.matching.motion import keyframe_twists

    try:
        kf_map = open_map(path)
        meta = kf_map.metadata
        table = kf_map.place_repetition
        dense = kf_map.dense_settings
        poses, stamps = np.asarray(kf_map.poses, np.float64), np.asarray(kf_map.timestamps_us, np.int64)
        kf_map.close()
    except ReRadarError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    info = meta.to_dict()
    # the stored place repetition: whether the default settings use it, and how many keyframes it marks
    default = LocalizationConfig()
    info["place_repetition"] = None if table is None else {
        "default_settings": table.settings == repetition_settings(default),
        "keyframes_marked": table.marked(default.max_place_repetition),
        "keyframes_unjudged": table.unjudged,
        "max_ratio": round(table.max_ratio, 4),
    }
    _, known = keyframe_twists(poses, stamps, default.motion)
    # under the default settings, as the rest of this report (a server's own are in its GET /maps)
    info["keyframe_motion"] = {"known": int(known.sum()), "keyframes": len(known),
                               "max_keyframe_gap_s": default.motion.max_keyframe_gap_s}
    # a far-view companion's dense images (the far view's dense registration): whether this version reads them
    from maps.database import FAR_VIEW
    from reradar_core.matching.dense import dense_image_settings

    info["dense_images"] = None if dense is None else {
        "default_settings": dense == dense_image_settings(FAR_VIEW.dense), "settings": dense}
    typer.echo(json.dumps(info, indent=2))
    if (message := motion_warning(poses, stamps, default, known)) is not None:
        typer.echo(f"warning: {message}", err=True)


def map_repetition_command(
    path: Path = typer.Argument(..., help="Map file (.h5)."),
    out: Path | None = typer.Option(None, "--out", help="Write the map with its place repetition here (.h5) instead "
                                    "of replacing PATH (replaced atomically: the old file stays whole until then)."),
    workers: int | None = typer.Option(None, "--workers", min=1, help="Threads (default: the usable cores, at most 4)."),
    overwrite: bool = typer.Option(False, help="Replace an existing --out file."),
) -> None:
    """Measure where a map repeats itself (every keyframe localized against the map, ~20-40 ms per keyframe and
    thread) and store it in the map, as `build-map` does since 2026-12-03: for maps built earlier or with
    --no-place-repetition, without their scans. Measured under the default localization settings; replaces a stored
    one. (A service configured with other settings measures maps it builds under its own.)"""
    from maps.build import add_place_repetition, unjudged_warning
    from reradar_core.localization import LocalizationConfig
    from reradar_core.paths import output_file

    if path.is_dir():
        typer.echo(f"error: {path} is a folder, not a map file (.h5)", err=True)
        raise typer.Exit(2)
    try:
        if out is not None:
            output_file(out, "--out", (".h5", ".hdf5"))
            if out.exists() and not overwrite:
                typer.echo(f"error: {out} exists; pass --overwrite to replace it", err=True)
                raise typer.Exit(2)
        table = add_place_repetition(path, out, workers=workers, show_progress=True, overwrite=overwrite)
    except ReRadarError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    marked = table.marked(LocalizationConfig().max_place_repetition)
    typer.echo(f"wrote {out or path}: place repetition of {len(table)} keyframes stored, {marked} marked "
               f"(largest repetition {table.max_ratio:.3f})")
    if (message := unjudged_warning(table, len(table))) is not None:
        typer.echo(f"warning: {message}", err=True)


def register(app: typer.Typer) -> None:
    """Add ``build-map``, ``map-info`` and ``map-repetition`` to the ``reradar`` command line."""
    app.command("build-map")(build_map_command)
    app.command("map-info")(map_info_command)
    app.command("map-repetition")(map_repetition_command)
