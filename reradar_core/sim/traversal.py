"""Per-traversal state: weather condition, season, parked cars that came or went, moving traffic, snow banks.

A traversal is one drive through a ``World``. Two traversals of one world share every static structure;
what a real revisit changes is drawn here from the traversal seed, deterministically.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from reradar_core.errors import ConfigError
from reradar_core.sim.world import ELEV_VEHICLE, Primitives, World, _hash_uniform, car_segments, stable_seed

__all__ = ["CONDITIONS", "Condition", "Traversal", "get_condition"]


@dataclass(frozen=True)
class Condition:
    """Weather / season effects on the radar image.

    Attributes:
        name: ``clear``, ``rain``, ``snow_cover`` or ``falling_snow``.
        noise_floor_db: added to the receiver noise floor, dB.
        attenuation_db_per_km: one-way atmospheric attenuation (two-way applied), dB/km.
        volume_clutter_per_m2: random per-scan backscatter points (rain drops / snow flakes) within 60 m.
        volume_clutter_rcs: their median cross-section.
        leaf_factor: scales foliage returns (0.35 = bare winter trees); canopy transparency rises with it.
        snow_banks: ploughed snow banks along the kerbs.
        ground_factor: scales diffuse ground backscatter (wet asphalt brighter, snow-covered ground smoother).
    """

    name: str
    noise_floor_db: float = 0.0
    attenuation_db_per_km: float = 0.0
    volume_clutter_per_m2: float = 0.0
    volume_clutter_rcs: float = 0.0
    leaf_factor: float = 1.0
    snow_banks: bool = False
    ground_factor: float = 1.0


CONDITIONS: dict[str, Condition] = {
    "clear": Condition("clear"),
    # no receiver-noise rise in weather (v3): a horizontal beam already sees a scene at ambient temperature,
    # so rain or snow in it cannot raise the antenna noise temperature measurably; what weather adds is
    # backscatter from the precipitation (volume clutter) and path attenuation (docs/SIMULATOR.md)
    "rain": Condition("rain", noise_floor_db=0.0, attenuation_db_per_km=10.0, volume_clutter_per_m2=0.03,
                      volume_clutter_rcs=0.02, leaf_factor=1.1, ground_factor=1.4),
    # v4: no path attenuation on a day without precipitation (like clear; v3: 2 dB/km) and ~1 dB/km in
    # falling dry snow (ice crystals scatter little and absorb less at 77 GHz: order 0.1-1 dB/km; v3: 12)
    "snow_cover": Condition("snow_cover", noise_floor_db=0.0, attenuation_db_per_km=0.0, leaf_factor=0.35,
                            snow_banks=True, ground_factor=0.6),
    "falling_snow": Condition("falling_snow", noise_floor_db=0.0, attenuation_db_per_km=1.0,
                              volume_clutter_per_m2=0.06, volume_clutter_rcs=0.03, leaf_factor=0.35,
                              snow_banks=True, ground_factor=0.6),
}


def get_condition(name: str | Condition) -> Condition:
    if isinstance(name, Condition):
        return name
    try:
        return CONDITIONS[name]
    except KeyError:
        raise ConfigError(f"unknown weather condition {name!r}; choose one of {sorted(CONDITIONS)}") from None


class Traversal:
    """One drive through ``world`` with its own seed and condition.

    Args:
        world: the persistent world.
        seed: traversal seed (traffic, parked cars, foliage, per-scan noise).
        condition: weather condition name or ``Condition``.
        traffic_per_km: moving vehicles per km of road.
        car_transmission: fraction of the beam passing over a car (parked or moving, not buses / trucks);
            ``None`` keeps the class default ``CAR_TRANSMISSION`` (opaque cars).
        traffic_lanes: lanes per direction of the moving traffic (simulator v5, multi-lane boulevards):
            each vehicle keeps one lane, 3.5 m wide, counted from ``median_m`` / 2 off the centreline.
            ``None`` (default, v4): every vehicle at 0.4 road half-widths off the centreline.
        median_m: width of the central median for ``traffic_lanes``, metres.
        ego_clearance_m: moving vehicles closer than this to the sensor are left out (they would overlap the
            ego vehicle); ``None`` keeps the class default ``EGO_CLEARANCE_M`` (7 m, v4), which also drops
            every vehicle in the lanes next to the ego's.
    """

    #: Fraction of parked-car slots holding a long-term parked car (same on every traversal) and the
    #: probability that any other slot is occupied on a given traversal.
    PERSISTENT_CAR_FRACTION = 0.35
    TRANSIENT_CAR_PROB = 0.3
    #: Parked and moving cars (not buses / trucks): reflectivity of their outline and the fraction of the
    #: beam passing over them (occlusion of what lies behind). v3: 2.5 and 0 (opaque).
    CAR_REFLECTIVITY = 2.5
    CAR_TRANSMISSION = 0.0
    #: Reflectivity of the ploughed snow banks along the kerbs (v3: 0.6).
    SNOW_BANK_REFLECTIVITY = 0.6
    #: One-way fraction of the beam passing a snow bank (what lies behind it stays visible; v4: 0.6). A
    #: ploughed bank is 0.5-1.5 m high, lower than the cars for which the Boreas suites take 0.8
    #: (docs/SIMULATOR.md, "ReFeree and RingKey: what the simulator gets wrong").
    SNOW_BANK_TRANSMISSION = 0.6
    #: Share of the 1 m kerb samples whose bank (70 % present) is drawn anew on every traversal; the others
    #: follow one pattern shared by every traversal of the world (driveways, hydrants, crossings are cleared
    #: at the same places every day). v4: 1.0, the whole pattern re-drawn per traversal.
    SNOW_BANK_DAILY_FRACTION = 1.0

    #: Lane width of the multi-lane traffic option, metres (Korean / UK urban arterials: 3.25-3.65 m).
    LANE_WIDTH_M = 3.5
    #: Moving vehicles closer than this to the sensor are left out (they would overlap the ego vehicle).
    EGO_CLEARANCE_M = 7.0

    def __init__(self, world: World, seed: int, condition: str | Condition = "clear", traffic_per_km: float = 12.0,
                 car_transmission: float | None = None, traffic_lanes: int | None = None, median_m: float = 0.0,
                 ego_clearance_m: float | None = None):
        self.world = world
        if ego_clearance_m is not None:
            self.EGO_CLEARANCE_M = float(ego_clearance_m)
        if car_transmission is not None:
            self.CAR_TRANSMISSION = float(car_transmission)
        self.seed = int(seed)
        self.condition = get_condition(condition)
        road = world.road
        rng = np.random.default_rng(stable_seed(self.seed, "traffic"))
        n = int(round(len(road.points) * road.spacing_m / 1000.0 * traffic_per_km))
        self._veh_idx0 = rng.uniform(0, len(road.points), n)
        self._veh_speed = rng.uniform(4.0, 14.0, n) * rng.choice([-1.0, 1.0], n)
        self._veh_lane = np.where(self._veh_speed > 0, -1.0, 1.0) * world.profile.road_half_width_m * 0.4
        if traffic_lanes is not None and n:
            # own generator: the draws above (and so the default traffic) stay as they were
            lane = np.random.default_rng(stable_seed(self.seed, "lanes")).integers(0, int(traffic_lanes), n)
            self._veh_lane = np.sign(self._veh_lane) * (0.5 * median_m + (lane + 0.5) * self.LANE_WIDTH_M)
        self._veh_size = np.column_stack([rng.uniform(4.2, 12.0, n), rng.uniform(1.8, 2.6, n)])
        self._veh_size[rng.random(n) < 0.8] = (4.6, 1.85)  # mostly cars, some buses / trucks

    def add_to_digest(self, h: Any) -> None:
        """Feed everything that decides this traversal's renders (world seed, profile, tile size and roads; own
        seed, condition, traffic draws and vehicle constants) into ``h``, a ``hashlib`` object (``render_key``)."""
        world = self.world
        for part in (world.seed, repr(world.profile), world.tile_m, self.seed, repr(self.condition),
                     self.EGO_CLEARANCE_M, self.CAR_TRANSMISSION):
            h.update(f"{part}\n".encode())
        for arr in (world.road.points, self._veh_idx0, self._veh_speed, self._veh_lane, self._veh_size):
            a = np.ascontiguousarray(arr)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())

    def parked_cars(self, prim: Primitives) -> np.ndarray:
        """(C, 3) x, y, yaw of the parked cars present on this traversal among ``prim``'s slots."""
        if len(prim.car_ids) == 0:
            return np.zeros((0, 3))
        persistent = _hash_uniform(prim.car_ids, 0x51A7) < self.PERSISTENT_CAR_FRACTION
        today = _hash_uniform(prim.car_ids, stable_seed(self.seed, "parked")) < self.TRANSIENT_CAR_PROB
        return prim.car_slots[persistent | today]

    def moving_vehicles(self, t_s: float, center_xy: np.ndarray, radius_m: float,
                        ego_clearance_m: float | None = None) -> np.ndarray:
        """(V, 5) x, y, yaw, length, width of moving vehicles near ``center_xy`` at time ``t_s``
        (none within ``ego_clearance_m``, default ``EGO_CLEARANCE_M``, of it)."""
        if ego_clearance_m is None:
            ego_clearance_m = self.EGO_CLEARANCE_M
        road = self.world.road
        n_road = len(road.points)
        if len(self._veh_idx0) == 0 or n_road < 2:
            return np.zeros((0, 5))
        idx = np.mod(self._veh_idx0 + self._veh_speed * t_s / road.spacing_m, n_road - 1)
        i = idx.astype(np.int64)
        p = road.points[i]
        near = np.hypot(*(p - center_xy).T)
        ok = (near < radius_m) & (near > ego_clearance_m)
        if not np.any(ok):
            return np.zeros((0, 5))
        i, p = i[ok], p[ok]
        tan = road.tangents[i]
        nrm = np.stack([-tan[:, 1], tan[:, 0]], axis=1)
        xy = p + self._veh_lane[ok, None] * nrm
        yaw = np.arctan2(tan[:, 1], tan[:, 0]) + np.where(self._veh_speed[ok] < 0, np.pi, 0.0)
        return np.column_stack([xy, yaw, self._veh_size[ok]])

    def dynamic_primitives(self, t_s: float, center_xy: np.ndarray, radius_m: float,
                           static: Primitives) -> Primitives:
        """Traversal-specific geometry near ``center_xy``: parked cars, moving vehicles, snow banks."""
        out = Primitives()
        if self.world.has_transient_clutter():
            key = self.seed if self.world.profile.ground_clutter_redraw == "traversal" else \
                stable_seed(self.seed, int(round(t_s * 1e6)))
            # the static world is queried out to the range plus the sweep's motion plus 5 m (sensor.py); 15 m
            # covers sweeps at up to 40 m/s
            xy, rcs = self.world.transient_clutter(center_xy, radius_m + 15.0, key)
            out.add_points(xy, rcs, 2)
        cars = self.parked_cars(static)
        if len(cars):
            out.add_segments(car_segments(cars), self.CAR_REFLECTIVITY, self.CAR_TRANSMISSION, 0.5, ELEV_VEHICLE)
        veh = self.moving_vehicles(t_s, center_xy, radius_m)
        if len(veh):
            from reradar_core.sim.world import rectangle_segments

            rects = [rectangle_segments(x, y, ln, wd, yaw) for x, y, yaw, ln, wd in veh]
            n_seg = np.array([len(r) for r in rects])
            car = np.repeat(veh[:, 3] <= 5.0, n_seg)  # cars vs buses / trucks (taller than the sensor: opaque)
            out.add_segments(np.concatenate(rects), np.where(car, self.CAR_REFLECTIVITY, 2.5),
                             np.where(car, self.CAR_TRANSMISSION, 0.0), 0.5, np.where(car, ELEV_VEHICLE, 0.0))
        if self.condition.snow_banks and self.world.profile.kerb_reflectivity > 0:
            road = self.world.road
            idx = np.asarray(road.tree.query_ball_point(center_xy, radius_m), dtype=np.int64)
            if len(idx):
                idx = idx[idx + 1 < len(road.points)]
                idx = idx[road.chain[idx] == road.chain[idx + 1]]
                w = self.world.profile.road_half_width_m + 0.3
                for side in (1.0, -1.0):
                    ids = idx.astype(np.uint64) * np.uint64(2) + np.uint64(side > 0)
                    present = _hash_uniform(ids, stable_seed(self.seed, "snowbank")) < 0.7
                    if self.SNOW_BANK_DAILY_FRACTION < 1.0:  # v4 (1.0): every sample drawn per traversal
                        daily = _hash_uniform(ids, stable_seed(self.world.seed, "snowbank-daily"))
                        fixed = _hash_uniform(ids, stable_seed(self.world.seed, "snowbank-fixed")) < 0.7
                        present = np.where(daily < self.SNOW_BANK_DAILY_FRACTION, present, fixed)
                    j = idx[present]
                    tan_a, tan_b = road.tangents[j], road.tangents[j + 1]
                    na = np.stack([-tan_a[:, 1], tan_a[:, 0]], axis=1)
                    nb = np.stack([-tan_b[:, 1], tan_b[:, 0]], axis=1)
                    seg = np.concatenate([road.points[j] + side * w * na, road.points[j + 1] + side * w * nb], axis=1)
                    d, _ = road.nearest(0.5 * (seg[:, :2] + seg[:, 2:]))
                    seg = seg[d > w - 0.8]
                    out.add_segments(seg, self.SNOW_BANK_REFLECTIVITY, self.SNOW_BANK_TRANSMISSION, 1.0, low=True)
        return out
