"""A persistent, tile-based 2-D radar world laid out around a road network.

The world is a function of (world seed, profile, road network) only: tile (ix, iy) is generated from a random
generator seeded with those three and the tile index, so any traversal of the same roads sees the same
buildings, walls, poles and trees, and the world can be arbitrarily long (tiles are generated lazily and
cached). Per-traversal changes (parked cars that came or went, seasonal foliage, snow banks, moving traffic)
are applied on top by ``Traversal`` from a traversal seed.

Geometry primitives (world frame, metres):

- segments ``(S, 4)`` x0, y0, x1, y1 with reflectivity (linear, relative radar cross-section per hit),
  one-way transmission (0 = opaque wall, 1 = no occlusion; vegetation and fences in between) and roughness
  (1 = diffuse, returns at any incidence; 0 = specular, returns only near normal incidence).
- discs ``(D, 3)`` x, y, radius: occluders with transmission (tree canopies), hit surface returns.
- points ``(P, 2)`` with a radar cross-section: poles, sign posts, leaves, ground clutter; not occluders.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from reradar_core.errors import ConfigError

__all__ = [
    "canonical_roads",
    "PROFILES",
    "Primitives",
    "RoadNetwork",
    "World",
    "WorldProfile",
    "stable_seed",
]

_MASK64 = (1 << 64) - 1
#: One-way transmission of building outlines: real scans show taller structures behind low façades.
BUILDING_TRANSMISSION = 0.0


def stable_seed(*parts: int | str) -> int:
    """A 63-bit seed from integers / strings, stable across runs and platforms (no Python ``hash``)."""
    h = 0x9E3779B97F4A7C15
    for p in parts:
        if isinstance(p, str):
            vals = [b for b in p.encode()]
        else:
            vals = [int(p) & _MASK64]
        for v in vals:
            h ^= v + 0x9E3779B97F4A7C15 + ((h << 6) & _MASK64) + (h >> 2)
            h &= _MASK64
            h = (h * 0xBF58476D1CE4E5B9) & _MASK64
            h ^= h >> 31
    return h & ((1 << 63) - 1)


def _hash_uniform(ids: np.ndarray, salt: int) -> np.ndarray:
    """Deterministic uniform [0, 1) per uint64 id and salt (splitmix64), vectorised."""
    with np.errstate(over="ignore"):
        z = ids.astype(np.uint64) ^ np.uint64(salt & _MASK64)
        z = z + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(1 << 53)


#: Elevation classes of segments (``Primitives.seg_low``): objects at ground level (kerbs, snow banks) are lit
#: through the ground's elevation pattern; vehicles below the antenna through ``SensorConfig.vehicle_elevation_scale``.
ELEV_GROUND = 1.0
ELEV_VEHICLE = 2.0


@dataclass(frozen=True)
class WorldProfile:
    """Densities and materials of one kind of environment. Densities are per 100 m of road or per hectare."""

    name: str
    road_half_width_m: float = 6.0
    building_prob_per_tile: float = 1.0      # mean buildings per 40 m tile near roads
    building_far_prob: float = 2.0           # mean buildings per tile far (> 45 m) from roads
    wall_per_tile: float = 0.8
    fence_per_tile: float = 0.8
    pole_spacing_m: float = 9.0
    street_tree_prob: float = 0.35           # per 8 m of roadside
    tree_per_tile: float = 1.0               # free-standing trees / bushes per tile
    hedge_per_tile: float = 0.5
    guard_rail_prob: float = 0.15            # per tile side
    parked_car_slot_prob: float = 0.7        # per 6.5 m of kerb
    ground_clutter_per_m2: float = 0.12
    ground_clutter_rcs: float = 0.02
    terrain_ridges_per_tile: float = 0.0     # off-road: rough terrain slopes
    kerb_reflectivity: float = 0.06
    frontage_prob: float = 0.8               # per tile and road side: a continuous row of façades
    # land use varies along a real route (terraces, open parkland, car parks, woods, fields): two smooth
    # random fields over ``zone_scale_m`` scale the built (buildings, walls, fences, façades) and the
    # vegetation (trees, hedges, terrain) densities by 1 +- zone_contrast; 0 = statistically uniform world
    # one-way transmission of building outlines: 0 = opaque; > 0 stands for what the elevation beam sees
    # over low buildings (taller structures behind them) in this 2-D world
    building_transmission: float = BUILDING_TRANSMISSION
    zone_contrast: float = 0.0
    zone_scale_m: float = 150.0
    # repetitive structure (simulator v5): > 0 draws every tile's random layout from one of this many tile
    # types (chosen per tile by a hash), so the same arrangement of buildings, trees, walls and clutter recurs
    # along the route as rows of identical apartment blocks or plantation stands do; 0 = every tile unique (v4)
    tile_types: int = 0
    # façade details (windows, pipes, balconies: hard point scatterers on building outlines) relative to v7's
    # density (3 per building segment near roads, 1.5 per metre of far walls); issue 10's near-range probe
    facade_detail_scale: float = 1.0
    # roughness of building outlines and walls relative to v10's (``Primitives.seg_rough``: 1 = diffuse,
    # 0 = specular); < 1 makes them return mostly near normal incidence; issue 10's specular-façade probe
    facade_roughness_scale: float = 1.0
    # regular roadsides (issue 10, session 26 probe): the share of tile sides (one side of the road in one tile,
    # chosen per tile and side by a hash) lined by regular rows instead of randomly placed roadside objects:
    # street trees of one size every ``roadside_tree_spacing_m`` at ``roadside_tree_setback_m`` beyond the road
    # edge, lamp posts every ``roadside_pole_spacing_m`` at ``roadside_pole_setback_m``, façade rows at a constant
    # setback (boulevard planting, plantation edges). On such a side the random poles and street trees are
    # dropped (their draws are still made, so the rest of the tile is unchanged); 0 = v1-v10 roadsides. The
    # spacings are whole numbers of road samples (2 m), Python-rounded: 5 m gives 4 m, 6 m gives 6 m
    roadside_regular: float = 0.0
    roadside_tree_spacing_m: float = 10.0
    roadside_tree_setback_m: float = 3.0
    roadside_tree_radius_m: float = 2.0
    roadside_pole_spacing_m: float = 30.0
    roadside_pole_setback_m: float = 1.0
    roadside_facade_setback_m: float = 4.75
    # control for the probe: > 0 moves each row tree and lamp post by U(-j, j) m along the road and across it,
    # so the rows keep their density, sizes and mean setback but lose their regularity; 0 = exact rows
    roadside_jitter_m: float = 0.0
    # open land (issue 10, simulator v11): the share of the road length that runs through land where a third
    # smooth random field over ``open_scale_m`` lies below its ``open_share``-quantile over the road samples;
    # there the built and vegetation densities are 0 (flat open moor, a loch shore): only the ground clutter, the
    # road's posts / sign plates / kerbs / rails and ``open_terrain`` x the zone's terrain ridges remain;
    # 0 = no open land (v1-v10)
    open_share: float = 0.0
    open_scale_m: float = 400.0
    # ground clutter that persists (issue 10, session 32 probe): the share of the ground-clutter points that are
    # part of the world (rocks, stumps, kerb stones); the rest is drawn anew, with the same density and RCS
    # distribution, on every traversal (``"traversal"``) or every scan (``"scan"``): returns of grass, heather and
    # gravel whose pattern within a resolution cell does not survive another run (wind, wetness, a viewpoint
    # centimetres off). 1.0 = v1-v10 (every point fixed in the world)
    ground_clutter_persistence: float = 1.0
    ground_clutter_redraw: str = "traversal"
    # the same share in open land only (``open_share``): open moor's heather and grass move with the wind
    open_clutter_persistence: float = 1.0
    # terrain ridges kept in open land, relative to the zone's density (0 = none: flat moor, a loch shore)
    open_terrain: float = 0.0


PROFILES: dict[str, WorldProfile] = {
    # nothing but the road: tests place known targets in it
    "empty": WorldProfile(
        "empty", building_prob_per_tile=0.0, building_far_prob=0.0, wall_per_tile=0.0, fence_per_tile=0.0,
        pole_spacing_m=1e12, street_tree_prob=0.0, tree_per_tile=0.0, hedge_per_tile=0.0, guard_rail_prob=0.0,
        parked_car_slot_prob=0.0, ground_clutter_per_m2=0.0, kerb_reflectivity=0.0, frontage_prob=0.0,
    ),
    "urban": WorldProfile("urban"),
    # suburban residential / commercial roads (the Boreas Glen Shields route): houses with driveways, so few
    # cars park on the street (v3 calibration, docs/SIMULATOR.md)
    "suburban": WorldProfile("suburban", parked_car_slot_prob=0.2),
    # wide multi-lane boulevards with sparse, set-back, repetitive buildings (MulRan DCC-like campus roads)
    "urban-open": WorldProfile(
        "urban-open", road_half_width_m=9.0, building_prob_per_tile=0.5, building_far_prob=1.0,
        wall_per_tile=0.3, fence_per_tile=0.4, pole_spacing_m=15.0, street_tree_prob=0.5, tree_per_tile=0.8,
        parked_car_slot_prob=0.2, frontage_prob=0.2,
    ),
    "offroad": WorldProfile(
        "offroad", road_half_width_m=3.5, building_prob_per_tile=0.05, building_far_prob=0.02,
        wall_per_tile=0.05, fence_per_tile=0.3, pole_spacing_m=150.0, street_tree_prob=0.25,
        tree_per_tile=4.0, hedge_per_tile=1.2, guard_rail_prob=0.0, parked_car_slot_prob=0.0,
        ground_clutter_per_m2=0.25, ground_clutter_rcs=0.035, terrain_ridges_per_tile=3.0,
        kerb_reflectivity=0.0, frontage_prob=0.0,
    ),
}


@dataclass
class Primitives:
    """World geometry in one area (see the module docstring for the arrays' meaning)."""

    seg: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    seg_refl: np.ndarray = field(default_factory=lambda: np.zeros(0))
    seg_trans: np.ndarray = field(default_factory=lambda: np.zeros(0))
    seg_rough: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # elevation class: 0 = taller than the antenna, lit at every range; ELEV_GROUND (kerb, bank); ELEV_VEHICLE
    seg_low: np.ndarray = field(default_factory=lambda: np.zeros(0))
    disc: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    disc_refl: np.ndarray = field(default_factory=lambda: np.zeros(0))
    disc_trans: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pts: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    pts_rcs: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pts_kind: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int8))  # 0 hard, 1 leaf, 2 ground
    # parked car slots: (C, 3) x, y, yaw and a persistent id each
    car_slots: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    car_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.uint64))

    @staticmethod
    def concat(parts: list[Primitives]) -> Primitives:
        out = Primitives()
        if not parts:
            return out
        for name in out.__dataclass_fields__:
            setattr(out, name, np.concatenate([getattr(p, name) for p in parts], axis=0))
        return out

    def add_segments(self, seg: np.ndarray, refl: np.ndarray | float, trans: np.ndarray | float,
                     rough: np.ndarray | float, low: bool | float | np.ndarray = False) -> None:
        """Append segments; ``low``: elevation class (False / 0, True / ``ELEV_GROUND``, ``ELEV_VEHICLE``)."""
        seg = np.asarray(seg, dtype=np.float64).reshape(-1, 4)
        n = len(seg)
        self.seg = np.concatenate([self.seg, seg])
        self.seg_refl = np.concatenate([self.seg_refl, np.broadcast_to(refl, (n,))])
        self.seg_trans = np.concatenate([self.seg_trans, np.broadcast_to(trans, (n,))])
        self.seg_rough = np.concatenate([self.seg_rough, np.broadcast_to(rough, (n,))])
        self.seg_low = np.concatenate([self.seg_low, np.broadcast_to(np.asarray(low, dtype=np.float64), (n,))])

    def add_points(self, xy: np.ndarray, rcs: np.ndarray | float, kind: int) -> None:
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        n = len(xy)
        self.pts = np.concatenate([self.pts, xy])
        self.pts_rcs = np.concatenate([self.pts_rcs, np.broadcast_to(rcs, (n,))])
        self.pts_kind = np.concatenate([self.pts_kind, np.full(n, kind, dtype=np.int8)])

    def add_discs(self, disc: np.ndarray, refl: np.ndarray | float, trans: np.ndarray | float) -> None:
        disc = np.asarray(disc, dtype=np.float64).reshape(-1, 3)
        n = len(disc)
        self.disc = np.concatenate([self.disc, disc])
        self.disc_refl = np.concatenate([self.disc_refl, np.broadcast_to(refl, (n,))])
        self.disc_trans = np.concatenate([self.disc_trans, np.broadcast_to(trans, (n,))])


def rectangle_segments(cx: float, cy: float, length: float, width: float, yaw: float) -> np.ndarray:
    """(4, 4) segments of a rectangle centred at (cx, cy), ``length`` along ``yaw``."""
    c, s = np.cos(yaw), np.sin(yaw)
    hl, hw = length / 2, width / 2
    corners = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
    xy = corners @ np.array([[c, s], [-s, c]]) + [cx, cy]
    return np.concatenate([xy, np.roll(xy, -1, axis=0)], axis=1)


def car_segments(slots: np.ndarray) -> np.ndarray:
    """(C, 3) x, y, yaw -> (4C, 4) outline segments of 4.6 m x 1.85 m cars."""
    if len(slots) == 0:
        return np.zeros((0, 4))
    return np.concatenate([rectangle_segments(x, y, 4.6, 1.85, yaw) for x, y, yaw in slots])


def canonical_roads(polylines: list[np.ndarray]) -> list[np.ndarray]:
    """The same road polylines in an order and direction that depend only on the set of roads.

    ``RoadNetwork`` resamples each polyline from its own start and keeps the earlier of two overlapping passes,
    so the roads [A, B] and [B, A], or A and A driven the other way, build different worlds (samples up to a
    spacing apart, kerbs and buildings placed from them). Each polyline is turned to run from its smaller end
    point (x, then y; a closed loop counter-clockwise), and the polylines are sorted by their points: every
    traversal that lists the same roads in any order or direction (``reradar sim --road``) shares one world.

    Args:
        polylines: (N_i, 2) float xy arrays, metres, world frame.

    Returns:
        New (N_i, 2) float64 arrays, the same points.
    """
    out = []
    for line in polylines:
        a = np.ascontiguousarray(np.asarray(line, dtype=np.float64).reshape(-1, 2))
        if len(a) >= 2:
            first, last = tuple(a[0]), tuple(a[-1])
            if first == last:  # a closed loop: counter-clockwise (shoelace area > 0)
                flip = float(np.sum(a[:-1, 0] * a[1:, 1] - a[1:, 0] * a[:-1, 1])) < 0.0
            else:
                flip = last < first
            if flip:
                a = np.ascontiguousarray(a[::-1])
        out.append(a)
    return sorted(out, key=lambda a: (-len(a), a.tobytes()))  # longer roads first: theirs are the kept samples


class RoadNetwork:
    """Road centrelines sampled every ``spacing_m`` with tangents; repeated passes are merged.

    Args:
        polylines: list of (N, 2) world-frame xy arrays (e.g. trajectories).
        spacing_m: resampling step along each polyline.
        merge_radius_m: samples closer than this to an earlier kept sample of another pass are dropped, so
            a road driven twice is one road.
    """

    def __init__(self, polylines: list[np.ndarray], spacing_m: float = 2.0, merge_radius_m: float = 4.0):
        pts, tans, chain = [], [], []
        kept_tree: cKDTree | None = None
        kept: list[np.ndarray] = []
        chain_id = 0
        for line in polylines:
            line = np.asarray(line, dtype=np.float64).reshape(-1, 2)
            rs = _resample(line, spacing_m)
            if len(rs) < 2:
                continue
            tan = np.gradient(rs, axis=0)
            tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-9)
            # Drop samples that revisit an already-kept road (within this pass too, beyond 30 m of arc).
            keep = np.ones(len(rs), dtype=bool)
            own = cKDTree(rs)
            pairs = own.query_pairs(merge_radius_m, output_type="ndarray")
            if len(pairs):
                far = np.abs(pairs[:, 0] - pairs[:, 1]) * spacing_m > 30.0
                later = np.maximum(pairs[far, 0], pairs[far, 1])
                keep[later] = False
            if kept_tree is not None:
                d, _ = kept_tree.query(rs, distance_upper_bound=merge_radius_m)
                keep &= ~np.isfinite(d)
            # a new chain id after every gap so kerbs are not drawn across dropped stretches
            breaks = np.concatenate([[True], ~keep[:-1]])
            ids = chain_id + np.cumsum(breaks & keep)
            chain_id = int(ids.max()) + 1
            pts.append(rs[keep])
            tans.append(tan[keep])
            chain.append(ids[keep])
            kept.append(rs[keep])
            kept_tree = cKDTree(np.concatenate(kept))
        if not pts:
            raise ConfigError("road network needs at least one polyline with two distinct points")
        self.points = np.concatenate(pts)
        self.tangents = np.concatenate(tans)
        self.chain = np.concatenate(chain)
        self.spacing_m = spacing_m
        self.tree = cKDTree(self.points)

    def nearest(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance to and index of the nearest road sample for (N, 2) points."""
        d, i = self.tree.query(np.asarray(xy).reshape(-1, 2))
        return d, i


def _resample(line: np.ndarray, step: float) -> np.ndarray:
    d = np.linalg.norm(np.diff(line, axis=0), axis=1)
    keep = np.concatenate([[True], d > 1e-6])
    line = line[keep]
    if len(line) < 2:
        return line
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    q = np.arange(0.0, s[-1], step)
    return np.stack([np.interp(q, s, line[:, 0]), np.interp(q, s, line[:, 1])], axis=1)


class World:
    """Deterministic tile-based world around ``road``.

    Args:
        road: the road network (shared by every traversal of this world).
        seed: world seed.
        profile: ``urban`` / ``offroad`` or a ``WorldProfile``.
        tile_m: tile side, metres.
        cache_tiles: how many generated tiles to keep in memory.
    """

    def __init__(self, road: RoadNetwork, seed: int = 0, profile: str | WorldProfile = "urban",
                 tile_m: float = 40.0, cache_tiles: int = 6000):
        if isinstance(profile, str):
            if profile not in PROFILES:
                raise ConfigError(f"unknown world profile {profile!r}; choose one of {sorted(PROFILES)}")
            profile = PROFILES[profile]
        self.road = road
        self.seed = int(seed)
        self.profile = profile
        self.tile_m = float(tile_m)
        self._cache: OrderedDict[tuple[int, int], Primitives] = OrderedDict()
        self._cache_tiles = cache_tiles
        self._open_thr: float | None = None
        self._open_tiles: dict[tuple[int, int], bool] = {}
        # transient clutter of one traversal, per tile (``ground_clutter_redraw`` "traversal": every scan of the
        # drive sees the same draw, so it is drawn once per tile)
        self._transient: OrderedDict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = OrderedDict()
        if profile.ground_clutter_redraw not in ("traversal", "scan"):
            raise ConfigError(f"ground_clutter_redraw must be 'traversal' or 'scan', not {profile.ground_clutter_redraw!r}")
        for name in ("open_share", "ground_clutter_persistence", "open_clutter_persistence"):
            if not 0.0 <= getattr(profile, name) <= 1.0:
                raise ConfigError(f"{name} must lie in [0, 1], not {getattr(profile, name)!r}")
        if not profile.open_terrain >= 0.0:
            raise ConfigError(f"open_terrain must be >= 0, not {profile.open_terrain!r}")
        if profile.open_share > 0 and not profile.open_scale_m > 0:
            raise ConfigError(f"open_scale_m must be > 0, not {profile.open_scale_m!r}")

    def tile(self, ix: int, iy: int) -> Primitives:
        key = (ix, iy)
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        prim = self._generate(ix, iy)
        self._cache[key] = prim
        if len(self._cache) > self._cache_tiles:
            self._cache.popitem(last=False)
        return prim

    def tiles_near(self, center_xy: np.ndarray, radius_m: float) -> list[tuple[int, int]]:
        """Indices (ix, iy) of the tiles with any point within ``radius_m`` of ``center_xy`` (world frame)."""
        cx, cy = float(center_xy[0]), float(center_xy[1])
        t = self.tile_m
        ix0, ix1 = int(np.floor((cx - radius_m) / t)), int(np.floor((cx + radius_m) / t))
        iy0, iy1 = int(np.floor((cy - radius_m) / t)), int(np.floor((cy + radius_m) / t))
        out = []
        for ix in range(ix0, ix1 + 1):
            for iy in range(iy0, iy1 + 1):
                # skip tiles entirely outside the circle
                nx = min(max(cx, ix * t), (ix + 1) * t)
                ny = min(max(cy, iy * t), (iy + 1) * t)
                if (nx - cx) ** 2 + (ny - cy) ** 2 <= radius_m ** 2:
                    out.append((ix, iy))
        return out

    def query(self, center_xy: np.ndarray, radius_m: float) -> Primitives:
        """All static primitives of tiles within ``radius_m`` of ``center_xy`` (world frame)."""
        return Primitives.concat([self.tile(ix, iy) for ix, iy in self.tiles_near(center_xy, radius_m)])

    # ------------------------------------------------------------------ generation
    def zone_factors(self, xy: np.ndarray) -> tuple[float, float]:
        """(built, vegetation) density factors at world point ``xy`` (both 1 when ``zone_contrast`` is 0).

        Value noise: uniform values on a ``zone_scale_m`` lattice (hashed from the world seed), interpolated
        with a smoothstep; factor = 1 + zone_contrast * (2 v - 1), so the mean density is unchanged.
        """
        pr = self.profile
        if pr.zone_contrast <= 0:
            return 1.0, 1.0
        built, veg = (max(0.0, 1.0 + pr.zone_contrast * (2.0 * self._value_noise(xy, pr.zone_scale_m, salt) - 1.0))
                      for salt in ("zone-built", "zone-veg"))
        return built, veg

    def is_open_land(self, xy: np.ndarray) -> bool:
        """True where world point ``xy`` (m) lies in open land (``WorldProfile.open_share``; False when 0, True
        everywhere when 1). What a tile holds is decided at its centre (``tile_is_open``)."""
        pr = self.profile
        if pr.open_share <= 0:
            return False
        if pr.open_share >= 1:
            return True
        return self._value_noise(xy, pr.open_scale_m, "zone-open") < self._open_threshold()

    def tile_is_open(self, ix: int, iy: int) -> bool:
        """Whether tile (ix, iy) is open land (its centre is; cached per tile)."""
        if self.profile.open_share <= 0:
            return False
        key = (ix, iy)
        if key not in self._open_tiles:
            self._open_tiles[key] = self.is_open_land(np.array([(ix + 0.5) * self.tile_m, (iy + 0.5) * self.tile_m]))
        return self._open_tiles[key]

    def _open_threshold(self) -> float:
        """The ``open_share``-quantile of the open-land field over the road samples of the whole road network
        (every route of this world together): they run through open land for that share of their length whatever
        the draw of the field (a route crosses only a few ``open_scale_m`` cells, so an area share would leave its
        own share to chance). At most ~4,000 samples, evenly strided."""
        if self._open_thr is None:
            pts = self.road.points[:: max(1, len(self.road.points) // 4000)]
            v = np.array([self._value_noise(p, self.profile.open_scale_m, "zone-open") for p in pts])
            self._open_thr = float(np.quantile(v, self.profile.open_share)) if len(v) else -1.0
        return self._open_thr

    def _value_noise(self, xy: np.ndarray, scale_m: float, salt: str) -> float:
        """Smoothstep-interpolated value noise in [0, 1) on a ``scale_m`` lattice hashed from the world seed."""
        g = np.asarray(xy, dtype=np.float64) / scale_m
        i0 = np.floor(g).astype(np.int64)
        f = g - i0
        f = f * f * (3 - 2 * f)
        s = stable_seed(self.seed, salt)
        v = 0.0
        for dx in (0, 1):
            for dy in (0, 1):
                cid = np.array([stable_seed(int(i0[0]) + dx, int(i0[1]) + dy)], dtype=np.uint64)
                w = (f[0] if dx else 1 - f[0]) * (f[1] if dy else 1 - f[1])
                v += w * float(_hash_uniform(cid, s)[0])
        return v

    def _generate(self, ix: int, iy: int) -> Primitives:
        pr = self.profile
        built, veg = self.zone_factors(np.array([(ix + 0.5) * self.tile_m, (iy + 0.5) * self.tile_m]))
        terrain = veg
        if self.tile_is_open(ix, iy):
            built, veg, terrain = 0.0, 0.0, pr.open_terrain * veg
        if built != 1.0 or veg != 1.0:
            pr = replace(pr, frontage_prob=min(1.0, pr.frontage_prob * built),
                         building_prob_per_tile=pr.building_prob_per_tile * built,
                         building_far_prob=pr.building_far_prob * built, wall_per_tile=pr.wall_per_tile * built,
                         fence_per_tile=pr.fence_per_tile * built,
                         street_tree_prob=pr.street_tree_prob * veg, tree_per_tile=pr.tree_per_tile * veg,
                         hedge_per_tile=pr.hedge_per_tile * veg,
                         terrain_ridges_per_tile=pr.terrain_ridges_per_tile * terrain)
        if pr.tile_types > 0:
            kind = int(_hash_uniform(np.array([stable_seed(ix, iy)], dtype=np.uint64),
                                     stable_seed(self.seed, "tile-type"))[0] * pr.tile_types)
            rng = np.random.default_rng(stable_seed(self.seed, pr.name, "type", kind))
        else:
            rng = np.random.default_rng(stable_seed(self.seed, pr.name, ix, iy))
        t = self.tile_m
        x0, y0 = ix * t, iy * t
        prim = Primitives()
        road = self.road
        w = pr.road_half_width_m
        # road samples inside this tile
        in_tile = np.nonzero(
            (road.points[:, 0] >= x0) & (road.points[:, 0] < x0 + t)
            & (road.points[:, 1] >= y0) & (road.points[:, 1] < y0 + t)
        )[0]

        def far_from_road(xy: np.ndarray, clearance: float) -> np.ndarray:
            d, _ = road.nearest(xy)
            return d >= clearance

        # --- roadside structure driven by the road samples in this tile
        if len(in_tile):
            p = road.points[in_tile]
            tan = road.tangents[in_tile]
            nrm = np.stack([-tan[:, 1], tan[:, 0]], axis=1)  # left normal

            def roadside_points(n: int, off_min: float, off_max: float, clearance: float) -> np.ndarray:
                """n points on either side of this tile's road, w + U(off_min, off_max) m from the
                centreline, dropping those within w + clearance of any road (intersections)."""
                j = rng.integers(0, len(p), n)
                side = rng.choice([-1.0, 1.0], n)
                off = w + rng.uniform(off_min, off_max, n)
                xy = p[j] + (side * off)[:, None] * nrm[j]
                return xy[far_from_road(xy, w + clearance)]

            nxt = in_tile + 1
            ok = (nxt < len(road.points))
            ok[ok] &= road.chain[nxt[ok]] == road.chain[in_tile[ok]]
            a_idx, b_idx = in_tile[ok], nxt[ok]
            pa, pb = road.points[a_idx], road.points[b_idx]
            na = np.stack([-road.tangents[a_idx, 1], road.tangents[a_idx, 0]], axis=1)
            nb = np.stack([-road.tangents[b_idx, 1], road.tangents[b_idx, 0]], axis=1)
            for side in (1.0, -1.0):
                if pr.kerb_reflectivity > 0:
                    kerb = np.concatenate([pa + side * w * na, pb + side * w * nb], axis=1)
                    kerb = kerb[far_from_road(0.5 * (kerb[:, :2] + kerb[:, 2:]), w - 0.5)]
                    # kerbs are low: they return weakly and do not block the view
                    prim.add_segments(kerb, pr.kerb_reflectivity * rng.uniform(0.5, 1.5, len(kerb)), 0.97, 1.0, low=True)
                if rng.random() < pr.guard_rail_prob:
                    off = w + 0.8
                    rail = np.concatenate([pa + side * off * na, pb + side * off * nb], axis=1)
                    rail = rail[far_from_road(0.5 * (rail[:, :2] + rail[:, 2:]), off - 0.5)]
                    prim.add_segments(rail, 1.5, 0.55, 0.35)
                    prim.add_points(rail[::1, :2], 1.2, 0)  # posts every sample
            # regular roadsides (``roadside_regular``): which sides of this tile's road are lined by rows
            regular_sides: tuple[float, ...] = ()
            if pr.roadside_regular > 0:
                u_side = _hash_uniform(np.array([stable_seed(ix, iy, 1), stable_seed(ix, iy, -1)],
                                                dtype=np.uint64), stable_seed(self.seed, pr.name, "roadside-regular"))
                regular_sides = tuple(sd for sd, u in zip((1.0, -1.0), u_side, strict=True)
                                      if u < pr.roadside_regular)
            # terraced façades: a continuous building line at a per-tile setback, with recesses and gaps
            for side in (1.0, -1.0):
                if len(a_idx) == 0 or rng.random() >= pr.frontage_prob:
                    continue
                sb = w + rng.uniform(2.5, 7.0)
                if side in regular_sides:
                    sb = w + pr.roadside_facade_setback_m
                off = np.full(len(a_idx), sb)
                recess = rng.random(len(a_idx)) < 0.15
                off[recess] += rng.uniform(0.5, 1.5, int(recess.sum()))
                fa = pa + side * off[:, None] * na
                fb = pb + side * off[:, None] * nb
                seg = np.concatenate([fa, fb], axis=1)
                # gaps between buildings / side alleys: runs of 2-8 samples (4-16 m) missing
                keep = np.ones(len(seg), dtype=bool)
                k = 0
                while k < len(seg):
                    if rng.random() < 0.08:
                        n_gap = int(rng.integers(2, 9))
                        keep[k:k + n_gap] = False
                        k += n_gap
                    k += 1
                keep &= far_from_road(0.5 * (fa + fb), sb - 0.5)
                seg = seg[keep]
                prim.add_segments(seg, rng.lognormal(np.log(2.0), 0.4, len(seg)), pr.building_transmission,
                                  pr.facade_roughness_scale * rng.uniform(0.5, 0.95, len(seg)))
                if len(seg):
                    n_det = int(rng.poisson(len(seg) * 3.0 * pr.facade_detail_scale))
                    k = rng.integers(0, len(seg), n_det)
                    u = rng.uniform(0, 1, n_det)[:, None]
                    prim.add_points(seg[k, :2] + u * (seg[k, 2:] - seg[k, :2]),
                                    rng.lognormal(np.log(2.0), 1.0, n_det), 0)
            # poles and signs
            if regular_sides:
                # the random roadside objects below are drawn as always, then those on a regular side dropped
                prim_all, prim = prim, Primitives()
            n_poles = rng.poisson(len(in_tile) * road.spacing_m / pr.pole_spacing_m)
            if n_poles:
                xy = roadside_points(n_poles, 0.4, 2.0, 0.2)
                prim.add_points(xy, rng.lognormal(np.log(4.0), 0.5, len(xy)), 0)
                prim.add_discs(np.column_stack([xy, np.full(len(xy), 0.15)]), 0.0, 0.0)
                # a sign plate next to some poles: a short strong segment
                sgn = xy[rng.random(len(xy)) < 0.3]
                if len(sgn):
                    ang = rng.uniform(0, np.pi, len(sgn))
                    d = 0.4 * np.stack([np.cos(ang), np.sin(ang)], axis=1)
                    prim.add_segments(np.concatenate([sgn - d, sgn + d], axis=1), 5.0, 0.3, 0.2)
            # street trees
            n_st = rng.poisson(len(in_tile) * road.spacing_m / 8.0 * pr.street_tree_prob)
            if n_st:
                xy = roadside_points(n_st, 1.5, 4.5, 1.0)
                self._add_trees(prim, rng, xy, rng.uniform(1.2, 3.0, len(xy)))
            if regular_sides:
                random_objects, prim = prim, prim_all
                prim = Primitives.concat([prim, self._drop_on_sides(random_objects, regular_sides)])
                self._add_regular_rows(prim, in_tile, regular_sides, ix, iy)
            # parked car slots along the kerb, inside the road edge
            if pr.parked_car_slot_prob > 0:
                n_slots = rng.binomial(len(in_tile) * 2, pr.parked_car_slot_prob * road.spacing_m / 6.5)
                if n_slots:
                    j = rng.integers(0, len(p), n_slots)
                    side = rng.choice([-1.0, 1.0], n_slots)
                    xy = p[j] + (side * (w - 1.3))[:, None] * nrm[j]
                    yaw = np.arctan2(tan[j, 1], tan[j, 0])
                    # avoid slots too close to another road's centreline (intersections)
                    okc = far_from_road(xy, w - 1.6)
                    slots = np.column_stack([xy, yaw])[okc]
                    # thin slots closer than 6 m to an earlier one
                    keep = []
                    for k in range(len(slots)):
                        if all(np.hypot(*(slots[k, :2] - slots[m, :2])) > 6.0 for m in keep):
                            keep.append(k)
                    slots = slots[keep]
                    prim.car_slots = np.concatenate([prim.car_slots, slots])
                    ids = rng.integers(0, np.iinfo(np.int64).max, len(slots), dtype=np.int64).astype(np.uint64)
                    prim.car_ids = np.concatenate([prim.car_ids, ids])

        if pr.tile_types > 0:
            # the road-independent layout below repeats exactly (relative to the tile) in tiles of one type
            rng = np.random.default_rng(stable_seed(self.seed, pr.name, "type-free", kind))
        # --- buildings (rectangles with façade recesses), oriented along the nearest road
        for far, lam in ((False, pr.building_prob_per_tile), (True, pr.building_far_prob)):
            for _ in range(rng.poisson(lam)):
                c = np.array([x0, y0]) + rng.uniform(0, t, 2)
                d, i = road.nearest(c)
                d, i = float(d[0]), int(i[0])
                if far != (d > 45.0):
                    continue
                tan = road.tangents[i]
                yaw = np.arctan2(tan[1], tan[0]) + rng.normal(0, 0.04)
                length, depth = rng.uniform(8, 32), rng.uniform(8, 20)
                setback = w + rng.uniform(2.5, 14.0)
                nrm = np.array([-tan[1], tan[0]])
                side = np.sign(np.dot(c - road.points[i], nrm)) or 1.0
                if d < setback + depth / 2:
                    c = road.points[i] + side * (setback + depth / 2) * nrm + rng.uniform(-t / 2, t / 2) * tan
                segs = _building_segments(rng, c, length, depth, yaw)
                ends = np.concatenate([segs[:, :2], 0.5 * (segs[:, :2] + segs[:, 2:])])
                if not np.all(far_from_road(ends, w + 1.5)):
                    continue
                # a little transmission stands for what the elevation beam sees over low buildings
                prim.add_segments(segs, rng.lognormal(np.log(2.0), 0.4, len(segs)), pr.building_transmission,
                                  pr.facade_roughness_scale * rng.uniform(0.5, 0.95, len(segs)))
                # façade details (windows, pipes, balconies): strong points on the walls
                n_det = int(rng.poisson(length * 1.5 * pr.facade_detail_scale))
                if n_det:
                    k = rng.integers(0, len(segs), n_det)
                    u = rng.uniform(0, 1, n_det)[:, None]
                    xy = segs[k, :2] + u * (segs[k, 2:] - segs[k, :2])
                    prim.add_points(xy, rng.lognormal(np.log(2.0), 1.0, n_det), 0)

        # --- walls and fences, roughly parallel to the nearest road
        for kind, lam in (("wall", pr.wall_per_tile), ("fence", pr.fence_per_tile)):
            for _ in range(rng.poisson(lam)):
                c = np.array([x0, y0]) + rng.uniform(0, t, 2)
                d, i = road.nearest(c)
                if d[0] < w + 1.0:
                    continue
                tan = road.tangents[int(i[0])]
                ang = np.arctan2(tan[1], tan[0]) + (rng.normal(0, 0.05) if rng.random() < 0.7
                                                    else np.pi / 2)
                length = rng.uniform(5, 30)
                n = max(1, int(length / 3.0))
                u = np.linspace(-length / 2, length / 2, n + 1)
                dirv = np.array([np.cos(ang), np.sin(ang)])
                pts = c + u[:, None] * dirv
                segs = np.concatenate([pts[:-1], pts[1:]], axis=1)
                segs = segs[far_from_road(0.5 * (segs[:, :2] + segs[:, 2:]), w + 0.8)]
                if kind == "wall":
                    prim.add_segments(segs, rng.lognormal(np.log(1.5), 0.3), 0.0, 0.5 * pr.facade_roughness_scale)
                else:
                    prim.add_segments(segs, rng.lognormal(np.log(0.8), 0.3), 0.5, 0.9)
                    prim.add_points(segs[:, :2], 1.0, 0)  # fence posts

        # --- free-standing trees / bushes and hedges
        n_tr = rng.poisson(pr.tree_per_tile)
        if n_tr:
            xy = np.array([x0, y0]) + rng.uniform(0, t, (n_tr, 2))
            xy = xy[far_from_road(xy, w + 2.0)]
            self._add_trees(prim, rng, xy, rng.uniform(1.0, 4.0, len(xy)))
        for _ in range(rng.poisson(pr.hedge_per_tile)):
            c = np.array([x0, y0]) + rng.uniform(0, t, 2)
            ang = rng.uniform(0, np.pi)
            length = rng.uniform(4, 20)
            dirv = np.array([np.cos(ang), np.sin(ang)])
            n = max(1, int(length / 2.0))
            u = np.linspace(-length / 2, length / 2, n + 1)
            pts = c + u[:, None] * dirv
            segs = np.concatenate([pts[:-1], pts[1:]], axis=1)
            segs = segs[far_from_road(0.5 * (segs[:, :2] + segs[:, 2:]), w + 1.0)]
            prim.add_segments(segs, 0.35, 0.35, 1.0)
            if len(segs):
                m = int(length * 3)
                k = rng.integers(0, len(segs), m)
                uu = rng.uniform(0, 1, m)[:, None]
                leaf = segs[k, :2] + uu * (segs[k, 2:] - segs[k, :2]) + rng.normal(0, 0.4, (m, 2))
                prim.add_points(leaf, rng.lognormal(np.log(0.15), 0.8, m), 1)

        # --- off-road terrain: rough slopes facing random directions (diffuse, semi-transparent)
        for _ in range(rng.poisson(pr.terrain_ridges_per_tile)):
            c = np.array([x0, y0]) + rng.uniform(0, t, 2)
            if not far_from_road(c[None], w + 3.0)[0]:
                continue
            ang = rng.uniform(0, np.pi)
            length = rng.uniform(8, 35)
            n = max(2, int(length / 2.5))
            u = np.linspace(-length / 2, length / 2, n + 1)
            dirv = np.array([np.cos(ang), np.sin(ang)])
            wob = np.cumsum(rng.normal(0, 0.5, n + 1))
            pts = c + u[:, None] * dirv + wob[:, None] * np.array([-dirv[1], dirv[0]])
            segs = np.concatenate([pts[:-1], pts[1:]], axis=1)
            prim.add_segments(segs, rng.lognormal(np.log(0.3), 0.5, len(segs)), 0.45, 1.0, low=True)

        # --- diffuse ground clutter (persistent texture), weaker on the asphalt
        xy, rcs = self._ground_clutter(rng, x0, y0, pr.ground_clutter_per_m2, pr)
        persistence = self.clutter_persistence(ix, iy)
        if persistence < 1.0 and len(xy):
            # own generator: the draws above stay as they were; the rest is drawn per traversal / scan
            keep = np.random.default_rng(stable_seed(self.seed, "clutter-keep", ix, iy)).random(len(xy))
            keep = keep < persistence
            xy, rcs = xy[keep], rcs[keep]
        if len(xy):
            prim.add_points(xy, rcs, 2)
        return prim

    def _ground_clutter(self, rng: np.random.Generator, x0: float, y0: float, per_m2: float,
                        pr: WorldProfile) -> tuple[np.ndarray, np.ndarray]:
        """Ground-clutter points of the tile at (x0, y0): (N, 2) world xy, (N,) RCS, weaker on the asphalt."""
        t = self.tile_m
        n_g = rng.poisson(per_m2 * t * t)
        if not n_g:
            return np.zeros((0, 2)), np.zeros(0)
        xy = np.array([x0, y0]) + rng.uniform(0, t, (n_g, 2))
        d, _ = self.road.nearest(xy)
        rcs = rng.lognormal(np.log(pr.ground_clutter_rcs), 1.0, n_g)
        rcs = np.where(d < pr.road_half_width_m, rcs * 0.25, rcs)
        return xy, rcs

    def clutter_persistence(self, ix: int, iy: int) -> float:
        """Share of tile (ix, iy)'s ground clutter fixed in the world (``ground_clutter_persistence``, or
        ``open_clutter_persistence`` in open land)."""
        pr = self.profile
        if self.tile_is_open(ix, iy):
            return pr.open_clutter_persistence
        return pr.ground_clutter_persistence

    def has_transient_clutter(self) -> bool:
        """Whether any ground clutter is drawn per traversal / scan (``transient_clutter``)."""
        pr = self.profile
        return pr.ground_clutter_persistence < 1.0 or (pr.open_share > 0 and pr.open_clutter_persistence < 1.0)

    def transient_clutter(self, center_xy: np.ndarray, radius_m: float, key: int) -> tuple[np.ndarray, np.ndarray]:
        """The non-persistent share of the ground clutter near ``center_xy`` (``clutter_persistence`` < 1), drawn
        from ``key`` (a traversal's or a scan's seed) with the tile's density and RCS distribution: (N, 2) world
        xy, (N,) RCS. Land-use zones and open land change the objects, not the clutter, so neither does this."""
        pr = self.profile
        if not self.has_transient_clutter():
            return np.zeros((0, 2)), np.zeros(0)
        t = self.tile_m
        xs, rs = [], []
        for ix, iy in self.tiles_near(center_xy, radius_m):
            share = 1.0 - self.clutter_persistence(ix, iy)
            if share <= 0:
                continue
            ck = (key, ix, iy)
            if ck in self._transient:
                self._transient.move_to_end(ck)
                xy, rcs = self._transient[ck]
            else:
                rng = np.random.default_rng(stable_seed(self.seed, "clutter-transient", key, ix, iy))
                xy, rcs = self._ground_clutter(rng, ix * t, iy * t, pr.ground_clutter_per_m2 * share, pr)
                if pr.ground_clutter_redraw == "traversal":  # a scan's key never comes back
                    self._transient[ck] = (xy, rcs)
                    if len(self._transient) > self._cache_tiles:
                        self._transient.popitem(last=False)
            xs.append(xy)
            rs.append(rcs)
        if not xs:
            return np.zeros((0, 2)), np.zeros(0)
        return np.concatenate(xs), np.concatenate(rs)

    def _side_of(self, xy: np.ndarray) -> np.ndarray:
        """+1 / -1: left / right of the nearest road sample's direction, for (N, 2) points."""
        if len(xy) == 0:
            return np.zeros(0)
        _, i = self.road.nearest(xy)
        tan = self.road.tangents[i]
        rel = xy - self.road.points[i]
        return np.where(rel[:, 1] * tan[:, 0] - rel[:, 0] * tan[:, 1] >= 0.0, 1.0, -1.0)

    def _drop_on_sides(self, prim: Primitives, sides: tuple[float, ...]) -> Primitives:
        """``prim`` (random roadside objects) without what stands on one of ``sides`` of the road."""
        out = Primitives()
        drop_p = np.isin(self._side_of(prim.pts), sides)
        drop_d = np.isin(self._side_of(prim.disc[:, :2]), sides)
        drop_s = np.isin(self._side_of(0.5 * (prim.seg[:, :2] + prim.seg[:, 2:])), sides)
        out.pts, out.pts_rcs, out.pts_kind = prim.pts[~drop_p], prim.pts_rcs[~drop_p], prim.pts_kind[~drop_p]
        out.disc, out.disc_refl, out.disc_trans = prim.disc[~drop_d], prim.disc_refl[~drop_d], prim.disc_trans[~drop_d]
        for name in ("seg", "seg_refl", "seg_trans", "seg_rough", "seg_low"):
            setattr(out, name, getattr(prim, name)[~drop_s])
        return out

    def _add_regular_rows(self, prim: Primitives, in_tile: np.ndarray, sides: tuple[float, ...], ix: int,
                          iy: int) -> None:
        """Rows of equal street trees and lamp posts at fixed spacings and setbacks on ``sides`` of the road
        samples ``in_tile``: a row slot is every k-th road sample (k = spacing / sample step), counted along the
        whole road network, so rows run on across tiles at one phase and both drives see the same rows."""
        pr, road = self.profile, self.road
        w = pr.road_half_width_m
        rrng = np.random.default_rng(stable_seed(self.seed, pr.name, "roadside-rows", ix, iy))
        nrm = np.stack([-road.tangents[in_tile, 1], road.tangents[in_tile, 0]], axis=1)
        for spacing, setback, kind in ((pr.roadside_tree_spacing_m, pr.roadside_tree_setback_m, "tree"),
                                       (pr.roadside_pole_spacing_m, pr.roadside_pole_setback_m, "pole")):
            if not spacing > 0:
                continue
            k = max(1, int(round(spacing / road.spacing_m)))
            slot = in_tile % k == 0
            xy = np.concatenate([road.points[in_tile[slot]] + side * (w + setback) * nrm[slot] for side in sides])
            d, _ = road.nearest(xy)
            ok = d >= w + setback - 0.5  # not across another road (intersections)
            xy = xy[ok]
            if pr.roadside_jitter_m > 0:
                tan = np.concatenate([road.tangents[in_tile[slot]] for _ in sides])[ok]
                out = np.concatenate([side * nrm[slot] for side in sides])[ok]
                j_along, j_across = rrng.uniform(-pr.roadside_jitter_m, pr.roadside_jitter_m, (2, len(xy), 1))
                xy = xy + j_along * tan + j_across * out
            if not len(xy):
                continue
            if kind == "tree":
                self._add_trees(prim, rrng, xy, np.full(len(xy), pr.roadside_tree_radius_m))
            else:
                prim.add_points(xy, 4.0, 0)
                prim.add_discs(np.column_stack([xy, np.full(len(xy), 0.15)]), 0.0, 0.0)

    @staticmethod
    def _add_trees(prim: Primitives, rng: np.random.Generator, xy: np.ndarray, radius: np.ndarray) -> None:
        """Trees: a trunk point, a partly transparent canopy disc and leaf/branch scatterers inside it."""
        if len(xy) == 0:
            return
        prim.add_points(xy, rng.lognormal(np.log(1.0), 0.4, len(xy)), 0)
        prim.add_discs(np.column_stack([xy, radius]), 0.25, rng.uniform(0.3, 0.6, len(xy)))
        m = (radius * radius * 6).astype(int) + 4
        owner = np.repeat(np.arange(len(xy)), m)
        ang = rng.uniform(0, 2 * np.pi, len(owner))
        rad = radius[owner] * np.sqrt(rng.uniform(0, 1, len(owner)))
        leaf = xy[owner] + rad[:, None] * np.stack([np.cos(ang), np.sin(ang)], axis=1)
        prim.add_points(leaf, rng.lognormal(np.log(0.12), 0.9, len(owner)), 1)


def _building_segments(rng: np.random.Generator, c: np.ndarray, length: float, depth: float,
                       yaw: float) -> np.ndarray:
    """Outline of a building with door recesses / bays on its long sides, (S, 4) world segments."""
    hl, hd = length / 2, depth / 2
    pts: list[tuple[float, float]] = []
    # front side (y = -hd, facing the road when rotated), from left to right with recesses
    for side_y, xs in ((-hd, (-hl, hl)), (hd, (hl, -hl))):
        n = int(rng.integers(1, 4))
        cuts = np.sort(rng.uniform(xs[0], xs[1], 2 * n)) if xs[0] < xs[1] else \
            np.sort(rng.uniform(xs[1], xs[0], 2 * n))[::-1]
        pts.append((xs[0], side_y))
        for k in range(n):
            a, b = cuts[2 * k], cuts[2 * k + 1]
            if abs(b - a) < 1.0 or rng.random() < 0.4:
                continue
            depth_in = rng.uniform(0.4, 1.5) * (1 if side_y < 0 else -1)
            pts += [(a, side_y), (a, side_y + depth_in), (b, side_y + depth_in), (b, side_y)]
        pts.append((xs[1], side_y))
    poly = np.asarray(pts)
    cc, ss = np.cos(yaw), np.sin(yaw)
    world = poly @ np.array([[cc, ss], [-ss, cc]]) + c
    segs = np.concatenate([world, np.roll(world, -1, axis=0)], axis=1)
    length_ok = np.linalg.norm(segs[:, 2:] - segs[:, :2], axis=1) > 1e-3
    return segs[length_ok]
