"""Calibration driver: render a small subset of a simulated suite with given simulator overrides and run the
baselines on it, so every row of the simulator's ablation table (docs/SIMULATOR.md) is reproducible by one
command.

The subset is a window of the suite's database drive (``--window a:b``, fractions of its scans) and up to
``--queries`` query scans of one query sequence whose ground-truth position lies within the window (nearest
database scan closer than half the recall radius, so the window's ends do not create queries without a match).
Recall@1 is over those queries (each has a true match): the paper's headline figure.

Overrides (``--set``, repeatable), applied on top of the suite's definition:

    sensor.FIELD=V               SensorConfig field (e.g. sensor.glint_db=0)
    cond.NAME.FIELD=V            Condition field of one weather condition (e.g. cond.rain.noise_floor_db=0);
                                 cond.*.FIELD applies to every condition
    profile.NAME.FIELD=V         WorldProfile field (e.g. profile.offroad.tree_per_tile=2)
    traversal.FIELD=V            Traversal option (traffic_per_km, persistent_car_fraction, transient_car_prob,
                                 car_reflectivity, car_transmission, snow_bank_reflectivity, traffic_lanes,
                                 median_m, ego_clearance_m, snow_bank_transmission, snow_bank_daily_fraction)
    query.lateral_m=V            the query drive's lateral offset from its route, metres
    query.seed=N, query.condition=NAME, query.offset=N
                                 the query drive's traversal seed, weather condition and first frame (session 13)
    db.lateral_m=V               the database drive's lateral offset from its route, metres (v5)
    db.every=N, query.every=N    frame step of the database / query drive (protocol spacing)
    db.condition=NAME            weather condition of the database drive (e.g. snow_cover: a winter map)
    query.sensor.FIELD=V         SensorConfig field of the query drive only (session 18: e.g. target_gain, a wet radome)
    route.speed_min=V, route.speed_max=V   cruise speed range of both drives (synthetic routes), m/s
    world.seed=N, route.seed=N   another world (its objects) / another synthetic route (both drives and the world's
                                 roads): a second calibration route of the same suite definition (session 29)
    world.grid_lines=N           a whole street grid around the loop route: its block lines extended across the
                                 area plus N more parallel streets each side (session 15 probe);
                                 world.grid_extend_m=V how far the lines reach beyond the route (default 300 m)
    route.max_lateral_accel=V    corner speed cap of both drives (synthetic routes), m/s^2 (session 14; 3.5 since
                                 simulator v9; "none" = v1-v8's corners at cruise speed)

Renders are cached under ``.cache/reradar/calib/`` by (suite, subset, overrides, simulator source hash), 0.3-1.3 GB
per full-suite probe; ``--no-cache`` neither reads nor writes them, ``reradar cache --prune`` removes them all.

Example (the off-road rows of the ablation table):

    OPENBLAS_NUM_THREADS=1 nice -n 5 python benchmarks/calibrate_sim.py --suite offroad-sim --window 0:0.4 \\
        --queries 100 --methods ringkey,raplace,radvlad,referee --set sensor.glint_db=0
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from reradar_core.io.scan import RadarScan  # noqa: E402
from reradar_core.paths import cache_dir  # noqa: E402
from reradar_core.sim import suites as S  # noqa: E402
from reradar_core.sim import traversal as T  # noqa: E402
from reradar_core.sim import world as W  # noqa: E402
from reradar_core.sim.sensor import SensorConfig, render_scan, scan_seed  # noqa: E402


def _parse_value(v: str) -> object:
    for cast in (int, float):
        try:
            return cast(v)
        except ValueError:
            pass
    if v.lower() in ("true", "false"):
        return v.lower() == "true"
    return v


def street_grid(route: S.RouteDef, extra: int, extend_m: float) -> list[np.ndarray]:
    """(2, 2) straight road centrelines of a street grid around a loop route (session 15 probe): every grid line of
    the route's blocks (``synthetic_loop_grid``), extended ``extend_m`` beyond the route's extent, plus
    ``extra`` parallel lines on each side at the route's mean block size. Metres, world frame."""
    from reradar_core.sim.trajectories import synthetic_loop_grid

    xs, ys = synthetic_loop_grid(route.seed, block_m=route.block_m, n_blocks=route.n_blocks)
    step = float(np.mean(route.block_m))
    xs = np.concatenate([xs.min() - step * np.arange(extra, 0, -1), xs, xs.max() + step * np.arange(1, extra + 1)])
    ys = np.concatenate([ys.min() - step * np.arange(extra, 0, -1), ys, ys.max() + step * np.arange(1, extra + 1)])
    x0, x1, y0, y1 = xs.min() - extend_m, xs.max() + extend_m, ys.min() - extend_m, ys.max() + extend_m
    return ([np.array([[x, y0], [x, y1]]) for x in xs] + [np.array([[x0, y], [x1, y]]) for y in ys])


def parse_overrides(items: list[str]) -> dict[str, object]:
    out: dict[str, object] = {}
    for it in items:
        if "=" not in it:
            raise SystemExit(f"--set {it!r}: expected KEY=VALUE")
        k, v = it.split("=", 1)
        out[k.strip()] = _parse_value(v.strip())
    return out


def _sim_source_hash() -> str:
    h = hashlib.sha256()
    for f in sorted((ROOT / "reradar_core" / "sim").glob("*.py")):
        h.update(f.read_bytes())
    return h.hexdigest()[:10]


def _condition(name: str, ov: dict[str, object]) -> T.Condition:
    c = T.CONDITIONS[name]
    kw = {k.split(".")[2]: v for k, v in ov.items()
          if k.startswith("cond.") and k.split(".")[1] in (name, "*")}
    return replace(c, **kw) if kw else c


def sensor_with(base: SensorConfig, ov: dict[str, object]) -> SensorConfig:
    """``base`` with the ``sensor.FIELD`` overrides."""
    kw = {k.split(".", 1)[1]: v for k, v in ov.items() if k.startswith("sensor.")}
    return replace(base, **kw) if kw else base  # type: ignore[arg-type]


def profile_with(base: W.WorldProfile, ov: dict[str, object]) -> W.WorldProfile:
    """``base`` with the ``profile.NAME.FIELD`` overrides of its own name."""
    kw = {k.split(".")[2]: v for k, v in ov.items() if k.startswith(f"profile.{base.name}.")}
    return replace(base, **kw) if kw else base  # type: ignore[arg-type]


def _traversal(world: W.World, seed: int, cond: T.Condition, ov: dict[str, object],
               traffic_per_km: float = 12.0, car_transmission: float = 0.0, traffic_lanes: int | None = None,
               median_m: float = 0.0, ego_clearance_m: float | None = None) -> T.Traversal:
    kw: dict[str, object] = {"traffic_per_km": traffic_per_km, "car_transmission": car_transmission,
                             "traffic_lanes": traffic_lanes, "median_m": median_m}
    if ego_clearance_m is not None:
        kw["ego_clearance_m"] = ego_clearance_m
    kw.update({k.split(".", 1)[1]: v for k, v in ov.items() if k.startswith("traversal.")})
    attrs = {"persistent_car_fraction": "PERSISTENT_CAR_FRACTION", "transient_car_prob": "TRANSIENT_CAR_PROB",
             "car_reflectivity": "CAR_REFLECTIVITY",
             "snow_bank_reflectivity": "SNOW_BANK_REFLECTIVITY", "ego_clearance_m": "EGO_CLEARANCE_M",
             "snow_bank_transmission": "SNOW_BANK_TRANSMISSION", "snow_bank_daily_fraction": "SNOW_BANK_DAILY_FRACTION"}
    trav = T.Traversal(world, seed, cond, **{k: v for k, v in kw.items() if k not in attrs})  # type: ignore[arg-type]
    for k, attr in attrs.items():
        if k in kw:
            setattr(trav, attr, float(kw[k]))  # type: ignore[arg-type]
    return trav


def subset_world(suite_name: str, ov: dict[str, object]) -> W.World:
    """The simulated world of a suite under the overrides ``ov`` (``world.seed``, ``route.seed``, ``world.grid_lines``,
    ``profile.*``): the one ``render_subset`` renders and the probes test positions in (``World.is_open_land``)."""
    suite = S.SUITES[suite_name]
    road_routes = suite.road_routes
    if "route.seed" in ov:
        if any(r.kind != "loop" for r in road_routes):
            raise SystemExit("route.seed applies to synthetic (loop) routes only")
        road_routes = tuple(replace(r, seed=int(ov["route.seed"])) for r in road_routes)  # type: ignore[call-overload]
    lines = [S._route_trajectory(replace(r, lateral_m=0.0), None).xy for r in road_routes]
    if "world.grid_lines" in ov:  # session 15: a whole street grid around the loop route (a planned district)
        lines += [g for r in road_routes if r.kind == "loop"
                  for g in street_grid(r, int(ov["world.grid_lines"]), float(ov.get("world.grid_extend_m", 300.0)))]  # type: ignore[arg-type]
    world_seed = int(ov["world.seed"]) if "world.seed" in ov else suite.world_seed  # type: ignore[call-overload]
    return W.World(W.RoadNetwork(lines), seed=world_seed, profile=profile_with(S.suite_profile(suite), ov))


def render_subset(suite_name: str, window: tuple[float, float], n_queries: int, query_seq: str | None,
                  ov: dict[str, object], db_every: int = 1, use_cache: bool = True,
                  all_queries: bool = False, revisit_m: float | None = None) -> dict[str, object]:
    """Render the database window and the chosen queries; returns scans, poses and the radius.

    ``all_queries``: take the query drive's scans evenly, whether or not the database holds their place (the
    paper's Recall@1 = TP / all queries, which is what it publishes for the MulRan single-session split);
    otherwise only queries with a database scan within ``revisit_m`` (default half the radius; a larger value
    keeps queries driven in a lane far from the database's, simulator v5)."""
    suite = S.SUITES[suite_name]
    db_def = next(s for s in suite.sequences if s.role == "database")
    q_defs = [s for s in suite.sequences if s.role == "query"]
    q_def = next(s for s in q_defs if s.name == query_seq) if query_seq else q_defs[0]
    if "db.every" in ov:
        db_def = replace(db_def, every=int(ov["db.every"]))  # type: ignore[call-overload]
    if "db.condition" in ov:  # e.g. a winter map (snow banks on both days) instead of the clear one
        db_def = replace(db_def, condition=str(ov["db.condition"]))
    if "query.every" in ov:
        q_def = replace(q_def, every=int(ov["query.every"]))  # type: ignore[call-overload]
    # the query drive's own randomness (traffic, parked cars, the day's snow banks, per-scan noise), weather and
    # first frame, to tell a condition's effect from its day's draw (session 13)
    if "query.seed" in ov:
        q_def = replace(q_def, traversal_seed=int(ov["query.seed"]))  # type: ignore[call-overload]
    if "query.condition" in ov:
        q_def = replace(q_def, condition=str(ov["query.condition"]))
    if "query.offset" in ov:
        q_def = replace(q_def, offset=int(ov["query.offset"]))  # type: ignore[call-overload]
    if "route.speed_max" in ov:  # drive speeds of both drives (protocol spacing at a fixed frame step)
        sp = (float(ov["route.speed_min"]), float(ov["route.speed_max"]))  # type: ignore[arg-type]
        db_def = replace(db_def, route=replace(db_def.route, speed_mps=sp))
        q_def = replace(q_def, route=replace(q_def.route, speed_mps=sp))
    if "route.max_lateral_accel" in ov:  # corner speed cap of both drives (the world's roads stay as they are)
        raw = str(ov["route.max_lateral_accel"])
        cap = None if raw.lower() == "none" else float(raw)
        db_def = replace(db_def, route=replace(db_def.route, max_lateral_accel_mps2=cap))
        q_def = replace(q_def, route=replace(q_def.route, max_lateral_accel_mps2=cap))
    if "route.seed" in ov:  # session 29: a second calibration route (same generator, other seed) for both drives
        rs = int(ov["route.seed"])  # type: ignore[call-overload]
        db_def = replace(db_def, route=replace(db_def.route, seed=rs))
        q_def = replace(q_def, route=replace(q_def.route, seed=rs))
    if "query.lateral_m" in ov:
        q_def = replace(q_def, route=replace(q_def.route, lateral_m=float(ov["query.lateral_m"])))  # type: ignore[arg-type]
    if "db.lateral_m" in ov:
        db_def = replace(db_def, route=replace(db_def.route, lateral_m=float(ov["db.lateral_m"])))  # type: ignore[arg-type]
    key = json.dumps([suite_name, window, n_queries, q_def.name, db_every, sorted(ov.items()), _sim_source_hash(),
                      all_queries] + ([revisit_m] if revisit_m is not None else []),
                     default=str)
    tag = hashlib.sha256(key.encode()).hexdigest()[:16]
    cache = Path(cache_dir("calib")) / f"{suite_name}-{tag}.npz"
    if use_cache and cache.is_file():
        z = np.load(cache, allow_pickle=False)
        return {k: z[k] for k in z.files} | {"radius": float(z["radius"]), "preset": str(z["preset"])}

    sensor = sensor_with(SensorConfig(**dict(suite.sensor_overrides)), ov)  # type: ignore[arg-type]
    # the query drive's own sensor differences (session 18: e.g. a wet radome on one run, ``query.sensor.target_gain``)
    q_sensor = sensor_with(sensor, {k[len("query."):]: v for k, v in ov.items() if k.startswith("query.sensor.")})
    world = subset_world(suite_name, ov)

    def times(seq: S.SequenceDef):
        traj = S._route_trajectory(seq.route, None)
        t, idx = S._sequence_times(traj, seq, use_pose_times=seq.route.kind != "loop")
        return traj, t, idx

    db_traj, db_t, db_idx = times(db_def)
    n = len(db_t)
    lo, hi = int(window[0] * n), int(np.ceil(window[1] * n))
    sel = np.arange(lo, hi, db_every)
    db_t, db_idx = db_t[sel], db_idx[sel]
    db_pose = db_traj.interpolate(db_t)
    q_traj, q_t, q_idx = times(q_def)
    q_pose = q_traj.interpolate(q_t)
    d = np.min(np.hypot(q_pose[:, None, 0] - db_pose[None, :, 0], q_pose[:, None, 1] - db_pose[None, :, 1]), axis=1)
    near = 0.5 * suite.radius_m if revisit_m is None else float(revisit_m)
    ok = np.arange(len(d)) if all_queries else np.nonzero(d < near)[0]
    if len(ok) > n_queries:
        ok = ok[np.linspace(0, len(ok) - 1, n_queries).round().astype(np.int64)]
    q_t, q_idx, q_pose = q_t[ok], q_idx[ok], q_pose[ok]

    def render(seq: S.SequenceDef, traj, t, idx, sensor: SensorConfig) -> np.ndarray:
        trav = _traversal(world, seq.traversal_seed, _condition(seq.condition, ov), ov, suite.traffic_per_km,
                          suite.car_transmission, suite.traffic_lanes, suite.median_m, suite.ego_clearance_m)
        out = []
        for t0, k in zip(t, idx, strict=True):
            s = render_scan(trav, traj, int(t0), suite.preset, scan_seed(trav.seed, int(k)), sensor)
            out.append(np.round(s.power * 255).astype(np.uint8))
        return np.stack(out)

    t0 = time.perf_counter()
    db_scans = render(db_def, db_traj, db_t, db_idx, sensor)
    q_scans = render(q_def, q_traj, q_t, q_idx, q_sensor)
    ms = 1e3 * (time.perf_counter() - t0) / (len(db_scans) + len(q_scans))
    res = {"db_scans": db_scans, "db_pose": db_pose, "db_t": db_t, "q_scans": q_scans, "q_pose": q_pose,
           "q_t": q_t, "radius": float(suite.radius_m), "preset": suite.preset, "render_ms": ms}
    if use_cache:  # 0.3-1.3 GB per full-suite probe: `reradar cache --prune` removes them all
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez(cache, **{k: np.asarray(v) for k, v in res.items()})
    return res


def add_route_arguments(ap: argparse.ArgumentParser, suite: str = "offroad-sim-hard",
                        model: str = "our-3-offroad-w05") -> None:
    """The options every ReRadar probe on a calibration route shares (``--suite --model --window --queries
    --revisit-m --set --label --json``; ``prepare_route`` reads them)."""
    ap.add_argument("--suite", default=suite)
    ap.add_argument("--model", default=model)
    ap.add_argument("--window", default="0:1")
    ap.add_argument("--queries", type=int, default=2000)
    ap.add_argument("--revisit-m", type=float, default=25.0)
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="as calibrate_sim.py --set")
    ap.add_argument("--label", default="")
    ap.add_argument("--json", type=Path, default=None)


@dataclass
class PreparedRoute:
    """A calibration route's render subset, every scan prepared by one method (``prepare_route``).

    Attributes: ``db`` / ``queries``: the method's prepared records; ``db_pose`` (N, 3) / ``q_pose`` (Q, 3):
    T_map_scan (m, rad); ``radius``: the suite's recall radius, m; ``overrides``: the parsed ``--set`` values."""

    db: list
    queries: list
    db_pose: np.ndarray
    q_pose: np.ndarray
    radius: float
    overrides: dict


def prepare_route(a: argparse.Namespace, method: object, use_cache: bool = True) -> PreparedRoute:
    """Render (or read from the render cache) the subset ``add_route_arguments``' options name and prepare every
    database and query scan with ``method`` (a ``PlaceRecognitionMethod``)."""
    ov = parse_overrides(a.overrides)
    w0, w1 = (float(x) for x in a.window.split(":"))
    data = render_subset(a.suite, (w0, w1), a.queries, None, ov, 1, use_cache, False, a.revisit_m)
    preset = str(data["preset"])

    def prepared(scans: object, times: object) -> list:
        return [method.prepare(_scan(s, int(t), preset)) for s, t in zip(scans, times, strict=True)]  # type: ignore[attr-defined, call-overload]

    return PreparedRoute(prepared(data["db_scans"], data["db_t"]), prepared(data["q_scans"], data["q_t"]),
                         np.asarray(data["db_pose"]), np.asarray(data["q_pose"]), float(data["radius"]), ov)  # type: ignore[arg-type]


def _scan(power_u8: np.ndarray, t0: int, preset: str) -> RadarScan:
    from reradar_core.io.presets import get_preset

    p = get_preset(preset)
    n_az = power_u8.shape[0]
    az_t = t0 + np.round(np.arange(n_az) * p.sweep_period_s * 1e6 / n_az).astype(np.int64)
    return RadarScan(power_u8.astype(np.float32) / 255.0, np.arange(n_az) * 2 * np.pi / n_az, az_t,
                     p.range_resolution_m, p.range_offset_m, preset=p.name)


def query_hits(method_name: str, data: dict[str, object]) -> np.ndarray:
    """(Q,) bool: one baseline's top-1 retrieval lies within the suite's radius of each query of the subset."""
    from reradar_core.baselines import make_method

    m = make_method(method_name)
    preset = str(data["preset"])
    db = [m.prepare(_scan(p, int(t), preset)) for p, t in zip(data["db_scans"], data["db_t"], strict=True)]  # type: ignore[call-overload]
    if m.needs_fit:
        m.fit(db)
    index = m.build_index([m.describe_prepared(r) for r in db])
    db_xy = np.asarray(data["db_pose"])[:, :2]
    q_pose = np.asarray(data["q_pose"])
    hits = np.zeros(len(q_pose), dtype=bool)
    for i, (p, t) in enumerate(zip(data["q_scans"], data["q_t"], strict=True)):  # type: ignore[call-overload]
        rec = m.prepare(_scan(p, int(t), preset))
        j = int(np.argmin(m.distance(m.describe_prepared(rec), index)))
        hits[i] = float(np.hypot(*(db_xy[j] - q_pose[i, :2]))) <= float(data["radius"])  # type: ignore[arg-type]
    return hits


def recall_at_1(method_name: str, data: dict[str, object]) -> float:
    """Recall@1 (%) of one baseline on the rendered subset: correct top-1 retrievals / all queries."""
    hits = query_hits(method_name, data)
    return 100.0 * float(hits.sum()) / max(len(hits), 1)


def emit_row(row: dict[str, object], json_path: Path | None) -> None:
    """Print one result row as JSON and append it to ``json_path`` (a JSON-lines file) when given."""
    print(json.dumps(row))
    if json_path is not None:
        with json_path.open("a") as f:
            f.write(json.dumps(row) + "\n")


#: Published real-data Recall@1 (%) of the baselines (paper, Tables OORD / MulRan / Boreas).
PUBLISHED: dict[str, dict[str, float]] = {
    "OORD Bellmouth 2-vs-1": {"raplace": 98.45, "radvlad": 98.87, "resnet18-netvlad": 97.67, "referee": 89.29,
                              "ringkey": 94.29},
    "OORD Hydro 1-vs-2": {"raplace": 92.65, "radvlad": 93.51, "resnet18-netvlad": 93.78, "referee": 90.13,
                          "ringkey": 91.15},
    "OORD Two Lochs 2-vs-1": {"raplace": 85.82, "radvlad": 84.27, "resnet18-netvlad": 5.41, "referee": 70.75,
                              "ringkey": 72.96},
    "MulRan DCC01": {"raplace": 64.71, "radvlad": 75.94, "resnet18-netvlad": 43.85, "referee": 54.55,
                     "ringkey": 54.01},
    "MulRan KAIST03": {"raplace": 92.98, "radvlad": 96.66, "resnet18-netvlad": 89.63, "referee": 87.63,
                       "ringkey": 86.29},
    "Boreas 2020-11-26": {"raplace": 94.93, "radvlad": 91.30, "resnet18-netvlad": 74.52, "referee": 73.67,
                          "ringkey": 58.33},
    "Boreas 2021-01-26": {"raplace": 96.99, "radvlad": 94.78, "resnet18-netvlad": 73.98, "referee": 69.47,
                          "ringkey": 65.31},
}
_ORDER = ("raplace", "radvlad", "resnet18-netvlad", "referee", "ringkey")
_NAMES = {"raplace": "RaPlace", "radvlad": "RadVLAD", "resnet18-netvlad": "ResNet18-NetVLAD*",
          "referee": "ReFeree", "ringkey": "RingKey"}


def calibration_table(rows: list[dict[str, object]], real: list[str]) -> str:
    """Markdown table: per (row, real sequence) and baseline, published vs simulated Recall@1, difference,
    within +-10 (ResNet18-NetVLAD exempt) and whether the five baselines' order is reproduced."""
    out = ["| simulated (subset) | stands for | method | published | simulated | diff | within ±10 |",
           "|---|---|---|---|---|---|---|"]
    for row, seq in zip(rows, real, strict=True):
        pub = PUBLISHED[seq]
        methods = [m for m in _ORDER if m in row]
        sim_order = sorted(methods, key=lambda m: -float(row[m]))  # type: ignore[arg-type]
        pub_order = sorted(methods, key=lambda m: -pub[m])
        where = f"{row['suite']}/{row['query_seq'] or 'default'} ({row['queries']} q, {row['db']} db)"
        for m in methods:
            d = float(row[m]) - pub[m]  # type: ignore[arg-type]
            ok = "exempt" if m == "resnet18-netvlad" else ("yes" if abs(d) <= 10 else "**no**")
            out.append(f"| {where} | {seq} | {_NAMES[m]} | {pub[m]:.1f} | {float(row[m]):.1f} | {d:+.1f} | {ok} |")  # type: ignore[arg-type]
        same = "yes" if sim_order == pub_order else "**no**"
        out.append(f"| {where} | {seq} | order | {' > '.join(_NAMES[m] for m in pub_order)} | "
                   f"{' > '.join(_NAMES[m] for m in sim_order)} | | {same} |")
    return "\n".join(out)


def _revisited(data: dict[str, object]) -> float:
    """Share (%) of the queries with a database scan within the recall radius (the Recall@1 ceiling)."""
    q, db = np.asarray(data["q_pose"])[:, :2], np.asarray(data["db_pose"])[:, :2]
    d = np.min(np.linalg.norm(q[:, None] - db[None], axis=2), axis=1)
    return 100.0 * float(np.mean(d <= float(data["radius"])))  # type: ignore[arg-type]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suite", default="offroad-sim", choices=sorted(n for n, s in S.SUITES.items()
                                                             if s.purpose in ("benchmark", "test")))
    ap.add_argument("--query-seq", default=None, help="query sequence name (default: the suite's first)")
    ap.add_argument("--window", default="0:1", help="fraction a:b of the database drive's scans")
    ap.add_argument("--db-every", type=int, default=1, help="take every N-th database scan in the window")
    ap.add_argument("--queries", type=int, default=100, help="at most this many queries (evenly spread)")
    ap.add_argument("--methods", default="ringkey,raplace,radvlad,referee")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="override KEY=VALUE")
    ap.add_argument("--label", default="", help="row label for the printed table")
    ap.add_argument("--json", type=Path, default=None, help="append the result as one JSON line here")
    ap.add_argument("--all-queries", action="store_true", help="queries evenly over the whole query drive, "
                    "revisits or not (the paper's MulRan Recall@1 divides by all queries)")
    ap.add_argument("--revisit-m", type=float, default=None, help="keep queries with a database scan within this "
                    "distance (default: half the recall radius)")
    ap.add_argument("--no-cache", action="store_true",
                    help="neither read nor write the render cache (a full-suite probe's renders take 0.3-1.3 GB; "
                         "`reradar cache --prune` removes cached ones)")
    ap.add_argument("--table", default=None, help="print the calibration table from these JSON-lines files "
                    "(comma-separated; rows chosen by --rows) and exit")
    ap.add_argument("--rows", default="", help="LABEL=REAL_SEQUENCE pairs for --table, ';'-separated")
    a = ap.parse_args(argv)
    if a.table is not None:
        lines = [ln for f in a.table.split(",") for ln in Path(f).read_text().splitlines() if ln.strip()]
        rows = {json.loads(ln)["label"]: json.loads(ln) for ln in lines}
        pairs = [p.split("=", 1) for p in a.rows.split(";") if p]
        print(calibration_table([rows[lab] for lab, _ in pairs], [seq for _, seq in pairs]))
        return 0
    ov = parse_overrides(a.overrides)
    w0, w1 = (float(x) for x in a.window.split(":"))
    t0 = time.perf_counter()
    data = render_subset(a.suite, (w0, w1), a.queries, a.query_seq, ov, a.db_every, not a.no_cache, a.all_queries,
                         a.revisit_m)
    t_render = time.perf_counter() - t0
    row: dict[str, object] = {"suite": a.suite, "query_seq": a.query_seq, "window": a.window,
                              "db": int(len(data["db_scans"])), "queries": int(len(data["q_scans"])),  # type: ignore[arg-type]
                              "overrides": ov, "label": a.label, "render_s": round(t_render, 1),
                              "all_queries": a.all_queries, "revisited_pct": round(_revisited(data), 1),
                              "revisit_m": a.revisit_m, "load1": round(os.getloadavg()[0], 2),
                              "utc": time.strftime("%H:%M:%S", time.gmtime())}
    for name in [s.strip() for s in a.methods.split(",") if s.strip()]:
        t1 = time.perf_counter()
        row[name] = round(recall_at_1(name, data), 1)
        row[f"{name}_s"] = round(time.perf_counter() - t1, 1)
    emit_row(row, a.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


__all__ = ["render_subset", "query_hits", "recall_at_1", "emit_row", "parse_overrides", "sensor_with", "profile_with", "calibration_table",
           "PUBLISHED"]
