"""``reradar sim``, ``reradar sim-suite`` and ``reradar sim-report`` commands."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import typer

from reradar_core.errors import ReRadarError

__all__ = ["register"]


def _fail(exc: Exception) -> typer.Exit:
    typer.echo(f"error: {exc}", err=True)
    return typer.Exit(2)


def _finite(value: float) -> float:
    if not math.isfinite(value):
        raise typer.BadParameter(f"must be a finite number of metres, got {value}")
    return value


def register(app: typer.Typer) -> None:
    from reradar_core.io.presets import PRESETS
    from reradar_core.sim.traversal import CONDITIONS
    from reradar_core.sim.world import PROFILES

    @app.command("sim")
    def sim(
        trajectory: Path = typer.Option(..., help="Pose file: Boreas radar_poses.csv, MulRan global_pose.csv or "
                                                  "a t,x,y,yaw CSV (metres, radians; time unit from --time-unit, "
                                                  "a t_s/t_ms/t_us/t_ns header, or absolute UTC times)."),
        time_unit: str = typer.Option(None, "--time-unit", help="Unit of the pose file's timestamps: s, ms, us "
                                      "or ns. Needed for relative times (e.g. a t,x,y,yaw CSV starting at 0); "
                                      "absolute UTC times and MulRan's ns need none. Never guessed."),
        out: Path = typer.Option(..., help="Output sequence folder (new or empty; or an earlier render, see "
                                 "above)."),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace an earlier render with other parameters "
                                       "in --out (only the files the simulator wrote are removed)."),
        preset: str = typer.Option("boreas", help=f"Radar preset: {', '.join(PRESETS)}."),
        layout: str = typer.Option(None, help="Dataset layout boreas/oxford/mulran (default: the preset's)."),
        profile: str = typer.Option("urban", help=f"World profile: {', '.join(PROFILES)}."),
        tile_types: int = typer.Option(0, min=0, help="Draw the world's 40 m tiles from this many layouts, so "
                                                      "places repeat (1: every tile the same, a street that repeats "
                                                      "itself every 40 m, as the confidence fit's periodic worlds); "
                                                      "0: every tile its own (the profile's default)."),
        condition: str = typer.Option("clear", help=f"Weather: {', '.join(CONDITIONS)}."),
        seed: int = typer.Option(0, help="World seed (same seed + same roads = same world)."),
        traversal_seed: int = typer.Option(None, help="Traversal seed (traffic, parked cars, noise); "
                                                      "default seed + 1."),
        road: list[Path] = typer.Option(None, help="Extra pose files whose paths are roads of the world "
                                                   "(give the other traversals' files to share one world: the "
                                                   "world depends on the set of roads, not on their order or "
                                                   "driving direction)."),
        lateral: float = typer.Option(0.0, callback=_finite, help="Drive this many metres left of the trajectory."),
        every: int = typer.Option(1, min=1, help="Keep every K-th scan."),
        limit: int = typer.Option(None, min=1, help="Render at most N scans."),
        sweep_from_poses: bool = typer.Option(None, "--sweep-from-poses/--tile-sweeps",
                                              help="Scan times = the pose times (4 Hz radar pose files) or "
                                                   "sweeps tiling the time span at 4 Hz; default: by pose rate."),
    ) -> None:
        """Render a simulated radar sequence along a trajectory, in a real dataset layout.

        An existing --out folder is resumed (scans already rendered are kept) only when it holds a render of
        exactly these parameters (trajectory, lateral offset, scan selection, preset, layout, world, traversal,
        weather; recorded in the folder); a render of other parameters is refused unless --overwrite. A folder
        holding anything else is refused.
        """
        from reradar_core.io.poses import TIME_UNITS
        from reradar_core.paths import output_dir
        from reradar_core.sim.sensor import SensorConfig
        from reradar_core.sim.trajectories import (
            check_render_trajectory,
            load_road_xy,
            load_trajectory,
            offset_trajectory,
            scan_times,
        )
        from reradar_core.sim.traversal import Traversal
        from reradar_core.sim.world import RoadNetwork, World, canonical_roads
        from reradar_core.sim.writer import render_sequence

        try:
            output_dir(out.parent, "--out")  # a file in the way is found before the trajectory is rendered
            if time_unit is not None and time_unit.strip().lower() not in TIME_UNITS:
                raise typer.BadParameter(f"--time-unit must be one of {sorted(TIME_UNITS)}, got {time_unit!r}")
            traj = load_trajectory(trajectory, time_unit)
            check_render_trajectory(traj, trajectory, time_unit.strip().lower() if time_unit else None)
            roads = [traj.xy] + [load_road_xy(r, time_unit) for r in (road or [])]
            # one world for every traversal that names the same roads, whichever it drives and in which direction
            world = World(RoadNetwork(canonical_roads(roads)), seed=seed, profile=profile)
            if tile_types:  # the profile's own name: the tiles draw from the same seeds
                world = World(world.road, seed=seed, profile=replace(world.profile, tile_types=tile_types))
            trav = Traversal(world, traversal_seed if traversal_seed is not None else seed + 1, condition)
            if lateral:
                traj = offset_trajectory(traj, lateral)
            all_t = scan_times(traj, every=1, use_pose_times=sweep_from_poses)
            idx = list(range(0, len(all_t), every))
            if limit is not None:
                idx = idx[:limit]
            render_sequence(out, trav, traj, all_t[idx], idx, preset, layout, SensorConfig(), True,
                            meta={"trajectory": str(trajectory), "trajectory_time_unit": time_unit or "from file",
                                  "lateral_m": lateral, **({"tile_types": tile_types} if tile_types else {})},
                            replace=overwrite)
        except ReRadarError as exc:
            raise _fail(exc) from exc
        span = (traj.timestamps_us[-1] - traj.timestamps_us[0]) / 1e6
        typer.echo(f"trajectory: {len(traj)} poses over {span:.1f} s, {traj.path_length_m():.1f} m")
        typer.echo(f"wrote {len(idx)} scans to {out}")

    @app.command("sim-suite")
    def sim_suite(
        name: str = typer.Argument(..., help="Suite: smoke, boreas-sim, loop-sim, loop-sim-hard, offroad-sim, "
                                             "offroad-sim-hard, calib-oxford, train-source, train-target-boreas, "
                                             "train-target-loop, train-target-loop-open, train-target-offroad; "
                                             "each train-target-X's look-alike sessions: train-target-X-lookalike "
                                             "(train-target-boreas-lookalike, train-target-loop-lookalike, "
                                             "train-target-loop-open-lookalike, train-target-offroad-lookalike); "
                                             "its periodic world (map drive and confidence sessions): "
                                             "train-target-X-periodic (train-target-boreas-periodic, "
                                             "train-target-loop-periodic, train-target-loop-open-periodic, "
                                             "train-target-offroad-periodic)."),
        root: Path = typer.Option(None, help="Output folder (default: sim/v<simulator version>/<name> in the "
                                  "cache, RERADAR_CACHE_DIR; with --every/--limit a sub-folder naming them)."),
        every: int = typer.Option(None, min=1, help="Override the suite's frame step."),
        limit: int = typer.Option(None, min=1, help="Cap scans per sequence."),
        trajectory_dir: Path = typer.Option(None, help="Folder with the real Boreas trajectories."),
    ) -> None:
        """Render a named benchmark suite, training split, look-alike or periodic suite (skips sequences already
        complete)."""
        from reradar_core.paths import output_dir
        from reradar_core.sim.suites import build_suite

        try:
            if root is not None:
                output_dir(root, "--root", create=False)
            data = build_suite(name, root, True, every, limit, trajectory_dir)
        except ReRadarError as exc:
            raise _fail(exc) from exc
        typer.echo(json.dumps({"name": data.name, "root": str(data.root), "preset": data.preset,
                               "layout": data.layout, "radius_m": data.radius_m, "purpose": data.purpose,
                               "database": [str(p) for p in data.database],
                               "queries": [str(p) for p in data.queries],
                               "query_conditions": data.query_conditions,
                               "training": [str(p) for p in data.training],
                               "confidence": [str(p) for p in data.confidence]}, indent=2))

    @app.command("sim-report")
    def sim_report(
        real: Path = typer.Option(..., help="Real scans: a sequence folder, or a folder of Navtech *.png scans."),
        sim: list[Path] = typer.Option(..., help="Simulated sequence folder(s); repeat for several conditions."),
        limit: int = typer.Option(12, min=1, help="Scans per folder."),
        preset: str = typer.Option(None, help="Radar preset of the scans (needed for 3,360-bin scans outside a "
                                   f"sequence folder: boreas, boreas-2021 or mulran); one of {', '.join(PRESETS)}."),
        images: Path = typer.Option(None, help="Write preview PNGs (polar + Cartesian): into this folder when it "
                                    "exists, else with this file-name prefix."),
    ) -> None:
        """Print real vs simulated scan statistics side by side (Markdown table)."""
        from reradar_core.paths import distinct_folder_labels, output_dir
        from reradar_core.sim.report import collect_scans, compare_table, folder_statistics, save_preview

        # one column per folder: the folder's name, or its last parts when two folders share a name
        labels = distinct_folder_labels(sim)
        if len(set(labels)) < len(labels):
            raise _fail(ReRadarError("--sim names the same folder twice"))
        try:
            prefix = None
            if images is not None:
                # (a Path never ends in '/': an existing folder is the one sign of "into")
                prefix = (output_dir(images, "--images") / "preview" if images.is_dir()
                          else output_dir(images.parent, "--images") / images.name)
            cols = {"real": folder_statistics(real, limit, preset)}
            for s, label in zip(sim, labels, strict=True):
                cols[label] = folder_statistics(s, limit, preset)
            written: list[Path] = []
            if prefix is not None:
                written += save_preview(collect_scans(real, 1, preset)[0], Path(f"{prefix}_real"))
                for s, label in zip(sim, labels, strict=True):
                    name = label.replace("/", "_")
                    written += save_preview(collect_scans(s, 1, preset)[0], Path(f"{prefix}_{name}"))
        except ReRadarError as exc:
            raise _fail(exc) from exc
        presets = {label: col.get("radar_preset") for label, col in cols.items()}
        if len({p for p in presets.values() if p}) > 1:  # e.g. Oxford scans beside Boreas-preset renders
            typer.echo("note: the folders are of different radar presets (" + ", ".join(
                f"{label}: {p}" for label, p in presets.items()) + "): their range bins differ in size, so the "
                "per-bin figures (power percentiles, keypoints) compare different grids; render with the real "
                "scans' preset (`reradar sim --preset`) for a like-for-like table", err=True)
        typer.echo(compare_table(cols))
        for path in written:
            typer.echo(f"wrote {path}", err=True)
