"""Scanning FMCW radar sensor model (Navtech CIR204 / CTS350-like), rendered directly in the polar domain.

Per scan (400 azimuths, 4 Hz, range bins per preset):

1. Each azimuth is cast from the sensor pose at its own timestamp (motion distortion), with ``oversample``
   sub-rays per azimuth cell so that thin gaps and edges are resolved.
2. Rays are intersected with the world's segments and discs, vectorised over (sub-ray, nearby primitive)
   pairs chosen by each primitive's azimuth interval. Every hit returns power (reflectivity x incidence
   factor); opaque hits shadow everything behind them, vegetation and fences only attenuate (transmission
   accumulated along the ray in a coarse range map).
3. Point scatterers (poles, leaves, façade details, ground clutter) project to (azimuth, range) from the
   pose at their azimuth's time and are attenuated by the same transmission map.
4. Power falls with range; a range-spread kernel and the antenna's two-way beam pattern (main lobe +
   sidelobes, circular across azimuth) blur the impulses; diffuse ground backscatter, the receiver noise
   floor and the bright near-field ring are added; multiplicative speckle (gamma); occasional multipath
   ghosts and interference (saturation) streaks; log compression to 8 bits.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from reradar_core.errors import ConfigError
from reradar_core.io.poses import PoseSequence
from reradar_core.io.presets import RadarPreset, get_preset
from reradar_core.io.scan import RadarScan
from reradar_core.sim.traversal import Traversal
from reradar_core.sim.world import ELEV_GROUND, ELEV_VEHICLE, Primitives, _hash_uniform, stable_seed

__all__ = ["SensorConfig", "render_scan", "sweep_poses"]


@dataclass(frozen=True)
class SensorConfig:
    """Sensor model parameters (defaults calibrated against real Oxford Navtech scans; docs/SIMULATOR.md).

    Attributes:
        oversample: sub-rays per azimuth cell for ray casting.
        beam_fwhm_deg: two-way main-lobe width (Navtech CTS350-X: ~1.8 deg).
        sidelobe_db: sidelobe pedestal relative to the main lobe peak, dB.
        sidelobe_halfwidth_bins: azimuth extent of the sidelobe pedestal on each side, in azimuth cells.
        range_sigma_m: Gaussian range spread of a point return, metres.
        range_tail_m: exponential tail of the range spread (multi-bounce / pulse tail), metres.
        range_exponent: received power of a target falls as (r_ref / r)^range_exponent.
        ref_range_m: reference range of the fall-off.
        noise_floor: receiver noise power (linear units of the same scale as the returns).
        ground_level: diffuse ground backscatter at its peak range.
        ground_peak_m: range of the ground clutter maximum (elevation beam pattern meets the ground).
        near_field_level: vehicle self-return power out to ``near_field_m`` (then a 0.2 m roll-off).
        speckle_looks: looks summed in the multiplicative speckle (1 = exponential intensity; 0 = none).
        speckle_range_cell: range bins per independent speckle cell (real scans: ~4-10 bins correlation).
        speckle_az_coupling: weight of neighbouring azimuths in the speckle (overlapping beams).
        db_floor, db_span: log compression: value = (10 log10(P) - db_floor) / db_span, clipped to [0, 1].
        streak_rate: mean interference streaks (saturated azimuths) per scan.
        ghost_prob: probability that one of the strongest returns produces a multipath ghost.
        min_range_m: returns nearer than this are ignored (the radome).
        target_gain: overall scale of target returns relative to the noise floor.
        glint_db: amplitude (dB) of the aspect-dependent fluctuation of every scatterer's cross-section
            (persistent per scatterer: 2..``glint_max_lobes`` lobes over a full turn); surfaces also vary
            along their length with period ``glint_length_m``. Makes returns change with the viewpoint
            as real ones do, so appearance matching degrades with the baseline.
        dominant_fraction: share of the power of hard returns (surfaces, poles, façade details: not leaves,
            ground clutter or precipitation) that is one dominant, steady scatterer per resolution cell rather
            than many random ones. Speckle is fully developed (exponential intensity) only for distributed
            clutter; a cell holding a dominant scatterer has Rician statistics (Swerling 0 plus diffuse part,
            Skolnik, Radar Handbook 3rd ed., ch. 7), so strong targets flicker far less between scans.
            0 = every return fully speckled.
        attitude_deg: standard deviation (degrees) of the vehicle's pitch and of its roll relative to the
            surrounding ground (simulator v5; 0 = level, v4). The elevation beam then meets the ground nearer
            on the side it tips towards and farther on the other, so the ground clutter, kerbs and terrain
            slopes it lights change with the azimuth and from one pass to the next. Pitch and roll vary
            smoothly with time (sum of sinusoids of 1.5-12 s periods, phases from the traversal seed).
        mount_height_m: height of the antenna above the ground (only used with ``attitude_deg``): the beam's
            depression angle in level attitude is atan(mount_height_m / ground_peak_m).
        vehicle_elevation_scale: cars (parked and moving; not buses / trucks, which are taller than the antenna)
            are lit through the ground's elevation pattern with its ranges scaled by this factor: a roof-mounted
            antenna looks over a car next to it, and an object whose top lies a fraction f of the antenna height
            below it meets the beam at the depression the ground meets at 1/f times its range, so f ~ 0.25 for a
            1.5 m car under a 2 m mount. 0 = cars lit at every range (v7).
        hard_point_gain: factor on the cross-section of the hard point scatterers (poles, façade details, posts,
            trunks; 1 = v7).
        azimuth_gain_db: standard deviation (dB) of a receive gain drawn afresh for every azimuth of every scan
            (0 = none, v1-v10): the level of a whole beam, targets and noise floor alike, jumps from one azimuth to
            the next and from one scan to the next, as in real Navtech scans (docs/SIMULATOR.md, "Beam levels").
        azimuth_floor_db: standard deviation (dB) of the noise floor's level, drawn afresh for every azimuth of
            every scan (0 = none, v1-v10): the receiver noise of real scans sits higher in some beams than in
            their neighbours, so the far range, which holds mostly noise, is bright in some beams and empty in
            others.
        skirt_dbc: level (dB relative to a return) of the range skirt every return spreads along its own beam
            at ``skirt_r0_m`` from it (None = no skirt, v1-v10). An FMCW radar's phase noise and range sidelobes
            spread part of a strong return's power over the whole beam, so a beam that hits a strong target near
            the vehicle is brighter at every range than its neighbours.
        skirt_r0_m, skirt_exponent: the skirt falls as (1 + |dr| / skirt_r0_m)^-skirt_exponent with the range
            offset dr from the return.
        azimuth_gain_coupling: weight of the two neighbouring azimuths in both draws (``[c, 1, c]`` smoothing,
            rescaled to the given standard deviation): the lag-1 correlation is 2c / (1 + 2c^2).
            Both draws come from their own random stream (seeded by the scan seed), so at 0 every other draw,
            and the render, is unchanged.
    """

    oversample: int = 2
    beam_fwhm_deg: float = 1.8
    sidelobe_db: float = -20.0
    sidelobe_halfwidth_bins: int = 10
    range_sigma_m: float = 0.12
    range_tail_m: float = 0.4
    range_exponent: float = 0.6
    ref_range_m: float = 20.0
    noise_floor: float = 1.0
    ground_level: float = 2.0
    ground_peak_m: float = 40.0
    near_field_level: float = 11.0
    near_field_m: float = 1.6
    speckle_looks: float = 1.0
    speckle_range_cell: int = 10
    speckle_az_coupling: float = 0.25
    db_floor: float = -3.5
    db_span: float = 100.0
    streak_rate: float = 0.5
    ghost_prob: float = 0.15
    min_range_m: float = 0.5
    target_gain: float = 2500.0
    glint_db: float = 6.0
    glint_max_lobes: int = 8
    glint_length_m: float = 3.0
    dominant_fraction: float = 0.0
    attitude_deg: float = 0.0
    mount_height_m: float = 2.0
    vehicle_elevation_scale: float = 0.0
    hard_point_gain: float = 1.0
    azimuth_gain_db: float = 0.0
    azimuth_floor_db: float = 0.0
    azimuth_gain_coupling: float = 0.0
    skirt_dbc: float | None = None
    skirt_r0_m: float = 1.0
    skirt_exponent: float = 2.0


def sweep_poses(trajectory: PoseSequence, t0_us: int, preset: RadarPreset, oversample: int = 1
                ) -> tuple[np.ndarray, np.ndarray]:
    """Sensor poses along one sweep starting at ``t0_us``.

    Returns:
        (A,) int64 azimuth timestamps [us] and (A * oversample, 3) world poses (x, y, yaw) of the sub-rays.
    """
    n_az = preset.num_azimuths
    dt_us = preset.sweep_period_s * 1e6 / n_az
    az_t = t0_us + np.round(np.arange(n_az) * dt_us).astype(np.int64)
    sub_t = t0_us + (np.arange(n_az * oversample) / oversample) * dt_us
    return az_t, trajectory.interpolate(sub_t)


@lru_cache(maxsize=8)
def _kernels(cfg: SensorConfig, range_res: float) -> tuple[np.ndarray, int, np.ndarray]:
    """(range kernel, its anchor index, azimuth kernel), float32, peak 1.

    Range: Gaussian core (+-3 sigma) plus a one-sided exponential tail out to 3 tau (returns smear away
    from the sensor); the kernel is asymmetric, so it is applied with its anchor at the core's centre.
    Azimuth: Gaussian main lobe (two-way FWHM) plus a raised sidelobe pedestal.
    """
    before = int(np.ceil(3 * cfg.range_sigma_m / range_res))
    after = int(np.ceil((3 * cfg.range_sigma_m + 3 * cfg.range_tail_m) / range_res))
    x = np.arange(-before, after + 1) * range_res
    k_r = np.exp(-0.5 * (x / cfg.range_sigma_m) ** 2)
    k_r = k_r + np.where(x > 0, np.exp(-x / max(cfg.range_tail_m, 1e-6)), 0.0) * 0.25
    k_r /= k_r.max()
    # OpenCV filters correlate (dst[x] = sum k[i] src[x + i - anchor]): flip so the tail trails the return
    k_r = k_r[::-1].copy()
    anchor = len(k_r) - 1 - before
    dth = 360.0 / 400.0
    hb = cfg.sidelobe_halfwidth_bins
    a = np.arange(-hb, hb + 1) * dth
    sigma = cfg.beam_fwhm_deg / 2.3548
    k_a = np.exp(-0.5 * (a / sigma) ** 2) + 10 ** (cfg.sidelobe_db / 10) * (1 + 0.5 * np.cos(np.pi * a / (hb * dth)))
    k_a /= k_a.max()
    return k_r.astype(np.float32), anchor, k_a.astype(np.float32)


def _point_ids(xy: np.ndarray) -> np.ndarray:
    """Persistent uint64 ids of world positions (millimetre grid), so glint phases are the same on every
    traversal."""
    q = np.round(np.asarray(xy, dtype=np.float64) * 1000.0).astype(np.int64)
    return (q[:, 0].astype(np.uint64) * np.uint64(73856093)) ^ (q[:, 1].astype(np.uint64) * np.uint64(19349663))


def _aspect_gain(ids: np.ndarray, angle: np.ndarray, cfg: SensorConfig) -> np.ndarray:
    """Multiplicative glint 10^(g sin(k angle + phase) / 10) with per-scatterer lobe count k and phase."""
    if cfg.glint_db <= 0 or len(ids) == 0:
        return np.ones(len(ids))
    k = 2.0 + np.floor(_hash_uniform(ids, 0x6C1) * (cfg.glint_max_lobes - 1))
    phase = 2 * np.pi * _hash_uniform(ids, 0x6C2)
    return 10.0 ** (cfg.glint_db / 10.0 * np.sin(k * angle + phase))


def _elevation_gain(r: np.ndarray, cfg: SensorConfig, peak: np.ndarray | None = None) -> np.ndarray:
    """Fraction of the elevation beam on the ground at range r (0 next to the vehicle, 1 beyond the peak).

    ``peak``: per-return ground-peak range (vehicle attitude, ``attitude_deg``); default ``cfg.ground_peak_m``."""
    if peak is None:
        return 1.0 / (1.0 + np.exp(-(r - 0.4 * cfg.ground_peak_m) / (0.15 * cfg.ground_peak_m)))
    return 1.0 / (1.0 + np.exp(-(r - 0.4 * peak) / (0.15 * peak)))


def attitude(traversal_seed: int, t_s: float, cfg: SensorConfig) -> tuple[float, float]:
    """(pitch, roll) in radians at time ``t_s``: smooth, zero-mean, std ``cfg.attitude_deg`` each."""
    if cfg.attitude_deg <= 0:
        return 0.0, 0.0
    rng = np.random.default_rng(stable_seed(traversal_seed, "attitude"))
    periods = rng.uniform(1.5, 12.0, (2, 6))
    phases = rng.uniform(0.0, 2 * np.pi, (2, 6))
    # the sum of six unit sinusoids has variance 3: scale to the requested std
    v = np.sin(2 * np.pi * t_s / periods + phases).sum(axis=1) / np.sqrt(3.0)
    return float(np.radians(cfg.attitude_deg) * v[0]), float(np.radians(cfg.attitude_deg) * v[1])


def _ground_peaks(theta: np.ndarray, pitch: float, roll: float, cfg: SensorConfig) -> np.ndarray:
    """Ground-peak range per sensor azimuth ``theta`` (clockwise from forward) for a tilted vehicle."""
    dep0 = np.arctan2(cfg.mount_height_m, cfg.ground_peak_m)
    dep = dep0 + pitch * np.cos(theta) - roll * np.sin(theta)
    return np.clip(cfg.mount_height_m / np.tan(np.clip(dep, np.radians(0.1), np.radians(60.0))), 3.0, 1000.0)


def _intervals(lo_ang: np.ndarray, span: np.ndarray, n_fine: int, dth_fine: float,
               margin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pair primitive index, pair fine-ray index) for primitives spanning [lo_ang, lo_ang + span] (clockwise)."""
    lo = np.floor(lo_ang / dth_fine - 0.5).astype(np.int64) - margin
    cnt = np.minimum(np.ceil(span / dth_fine).astype(np.int64) + 2 * margin + 2, n_fine)
    owner = np.repeat(np.arange(len(lo)), cnt)
    start = np.repeat(np.cumsum(cnt) - cnt, cnt)
    ray = (lo[owner] + (np.arange(len(owner)) - start)) % n_fine
    return owner, ray


def _to_sensor(xy: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World xy -> (clockwise azimuth in [0, 2pi), range) in the sensor frame of ``pose``."""
    dx, dy = xy[..., 0] - pose[..., 0], xy[..., 1] - pose[..., 1]
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    x = c * dx + s * dy
    y = -s * dx + c * dy
    return np.mod(np.arctan2(-y, x), 2 * np.pi), np.hypot(x, y)


def render_scan(traversal: Traversal, trajectory: PoseSequence, t0_us: int, preset: str | RadarPreset,
                scan_seed: int, config: SensorConfig = SensorConfig(), extra: Primitives | None = None
                ) -> RadarScan:
    """Render one sweep starting at ``t0_us`` (first azimuth) along ``trajectory``.

    Args:
        traversal: world + per-traversal state (condition, traffic, parked cars).
        trajectory: T_world_sensor poses; interpolated at every sub-ray's time.
        t0_us: sweep start time, microseconds.
        preset: radar preset (range resolution, bin count, azimuths, sweep period).
        scan_seed: seed of this scan's noise (derive it from (traversal seed, scan index)).
        config: sensor model parameters.
        extra: additional primitives (tests place known targets with it).

    Returns:
        RadarScan with power in [0, 1] quantised to 1/255, per-azimuth timestamps, uniform azimuths.

    Raises:
        ConfigError: ``scan_seed`` not a non-negative int (None would draw fresh noise on every call), or ``t0_us``
            outside the trajectory's time span (e.g. seconds or milliseconds), where the pose look-up would hold
            its end pose and render the sweep somewhere else.
    """
    p = get_preset(preset)
    if isinstance(scan_seed, bool) or not isinstance(scan_seed, (int, np.integer)) or scan_seed < 0:
        raise ConfigError(f"scan_seed must be a non-negative int (sim.writer.scan_seed(traversal seed, scan "
                          f"index)), got {scan_seed!r}")
    ts = trajectory.timestamps_us
    if len(ts) and not (int(ts[0]) - p.sweep_period_s * 1e6 <= t0_us <= int(ts[-1])):
        raise ConfigError(f"t0_us {t0_us} lies outside the trajectory's times [{int(ts[0])}, {int(ts[-1])}] "
                          "(microseconds): give the sweep's start in the trajectory's time, in microseconds")
    cfg = config
    cond = traversal.condition
    rng = np.random.default_rng(scan_seed)
    n_az, n_r, K = p.num_azimuths, p.num_range_bins, cfg.oversample
    n_fine = n_az * K
    dth = 2 * np.pi / n_az
    dth_f = dth / K
    res, off = p.range_resolution_m, p.range_offset_m
    max_r = p.max_range_m
    az_t, poses = sweep_poses(trajectory, t0_us, p, K)
    theta = (np.arange(n_fine) + 0.5) * dth_f - dth / 2  # sub-ray sensor azimuths (clockwise)
    phi = poses[:, 2] - theta  # world direction angle of each sub-ray
    ox, oy = poses[:, 0], poses[:, 1]
    dx, dy = np.cos(phi), np.sin(phi)
    mid = poses[n_fine // 2]
    motion = float(np.hypot(*(poses[-1, :2] - poses[0, :2]))) + 1e-3
    dyaw = float(abs(np.angle(np.exp(1j * (poses[-1, 2] - poses[0, 2])))))
    t_mid_s = (t0_us + 0.5 * p.sweep_period_s * 1e6) / 1e6

    pitch, roll = attitude(traversal.seed, t_mid_s, cfg)
    peak_f = _ground_peaks(theta, pitch, roll, cfg) if cfg.attitude_deg > 0 else None  # per fine ray

    prim = traversal.world.query(mid[:2], max_r + motion + 5.0)
    dyn = traversal.dynamic_primitives(t_mid_s, mid[:2], max_r, prim)
    prim = Primitives.concat([prim, dyn] + ([extra] if extra is not None else []))

    # ---------------- ray casting against segments
    hit_ray, hit_t, hit_amp, hit_tr, hit_coh = [], [], [], [], []
    if len(prim.seg):
        s = prim.seg
        a0, r0 = _to_sensor(s[:, :2], mid)
        a1, r1 = _to_sensor(s[:, 2:], mid)
        near_enough = np.minimum(r0, r1) < max_r + motion + 5
        s, a0, a1, r0, r1 = s[near_enough], a0[near_enough], a1[near_enough], r0[near_enough], r1[near_enough]
        refl, tr, rough = (prim.seg_refl[near_enough], prim.seg_trans[near_enough], prim.seg_rough[near_enough])
        low = prim.seg_low[near_enough]
        d = np.angle(np.exp(1j * (a1 - a0)))  # clockwise signed span
        lo_ang = np.where(d >= 0, a0, a1)
        span = np.abs(d)
        ev = s[:, 2:] - s[:, :2]
        seg_len = np.maximum(np.hypot(ev[:, 0], ev[:, 1]), 1e-9)
        # distance from the mid pose to the segment bounds how far motion moves its azimuth interval
        w = mid[:2] - s[:, :2]
        u = np.clip((w[:, 0] * ev[:, 0] + w[:, 1] * ev[:, 1]) / seg_len ** 2, 0, 1)
        dist = np.hypot(*(s[:, :2] + u[:, None] * ev - mid[:2]).T)
        margin = np.ceil((motion / np.maximum(dist, 0.5) + dyaw) / dth_f).astype(np.int64) + 1
        margin = np.minimum(margin, n_fine // 2)
        si, ri = _intervals(lo_ang, span, n_fine, dth_f, margin)
        ex, ey = ev[si, 0], ev[si, 1]
        wx, wy = s[si, 0] - ox[ri], s[si, 1] - oy[ri]
        rdx, rdy = dx[ri], dy[ri]
        den = rdx * ey - rdy * ex
        ok = np.abs(den) > 1e-9
        den = np.where(ok, den, 1.0)
        t = (wx * ey - wy * ex) / den
        uu = (wx * rdy - wy * rdx) / den
        ok &= (t > cfg.min_range_m) & (t < max_r) & (uu >= 0) & (uu <= 1)
        si, ri, t, den = si[ok], ri[ok], t[ok], den[ok]
        cos_inc = np.abs(den) / seg_len[si]
        amp = refl[si] * (rough[si] * cos_inc + (1 - rough[si]) * cos_inc ** 8) / K
        # objects at ground level are lit only where the elevation beam reaches the ground
        peak_hit = None if peak_f is None else peak_f[ri]
        amp = np.where(low[si] == ELEV_GROUND, amp * _elevation_gain(t, cfg, peak_hit), amp)
        if cfg.vehicle_elevation_scale > 0:  # cars: the same pattern, its ranges scaled (``SensorConfig``)
            veh_peak = cfg.vehicle_elevation_scale * (cfg.ground_peak_m if peak_hit is None else peak_hit)
            amp = np.where(low[si] == ELEV_VEHICLE, amp * _elevation_gain(t, cfg, veh_peak), amp)
        # glint along the surface and with the viewing direction (windows, seams, ribs of a façade)
        seg_ids = _point_ids(0.5 * (s[:, :2] + s[:, 2:]))
        view = np.arctan2(rdy, rdx)[ok] + uu[ok] * seg_len[si] * (2 * np.pi / cfg.glint_length_m)
        amp = amp * _aspect_gain(seg_ids[si], view, cfg)
        hit_ray.append(ri)
        hit_t.append(t)
        hit_amp.append(amp)
        hit_tr.append(tr[si])
        hit_coh.append(np.ones(len(t), bool))
    # ---------------- discs (tree canopies, pole shadows)
    if len(prim.disc):
        c = prim.disc
        ac, rc = _to_sensor(c[:, :2], mid)
        keep = (rc < max_r + motion + 5) & (rc > c[:, 2] + 0.3)
        c, ac, rc = c[keep], ac[keep], rc[keep]
        refl, tr = prim.disc_refl[keep], prim.disc_trans[keep]
        half = np.arcsin(np.clip(c[:, 2] / rc, 0, 1))
        margin = np.ceil((motion / np.maximum(rc, 0.5) + dyaw) / dth_f).astype(np.int64) + 1
        margin = np.minimum(margin, n_fine // 2)
        di, ri = _intervals(ac - half, 2 * half, n_fine, dth_f, margin)
        wx, wy = c[di, 0] - ox[ri], c[di, 1] - oy[ri]
        proj = wx * dx[ri] + wy * dy[ri]
        perp2 = wx * wx + wy * wy - proj * proj
        rad2 = c[di, 2] ** 2
        ok = (perp2 < rad2) & (proj > 0)
        t = proj[ok] - np.sqrt(rad2[ok] - perp2[ok])
        ok2 = (t > cfg.min_range_m) & (t < max_r)
        hit_ray.append(ri[ok][ok2])
        hit_t.append(t[ok2])
        hit_amp.append(refl[di[ok][ok2]] * cond.leaf_factor / K)
        hit_tr.append(1 - (1 - tr[di[ok][ok2]]) * min(1.0, cond.leaf_factor))
        hit_coh.append(np.zeros(int(ok2.sum()), bool))  # canopy: many leaves, distributed
    if hit_ray:
        h_ray = np.concatenate(hit_ray)
        h_t = np.concatenate(hit_t)
        h_amp = np.concatenate(hit_amp)
        h_tr = np.concatenate(hit_tr)
        h_coh = np.concatenate(hit_coh)
    else:
        h_ray = np.zeros(0, np.int64)
        h_t = h_amp = h_tr = np.zeros(0)
        h_coh = np.zeros(0, bool)

    # ---------------- transmission map on a coarse range grid (two-way, log domain, cumulative)
    coarse = 8
    n_c = (n_r + coarse - 1) // coarse
    cb = np.floor((h_t - off) / (res * coarse)).astype(np.int64) + 1
    okc = cb < n_c
    lt = 2.0 * np.log(np.maximum(h_tr, 1e-4))
    tmap = np.bincount(h_ray[okc] * n_c + cb[okc], weights=lt[okc], minlength=n_fine * n_c)
    tmap = np.exp(np.cumsum(tmap.reshape(n_fine, n_c), axis=1)).astype(np.float32)
    # hits are shadowed by what lies before them (not by themselves: their own term starts one cell later)
    hb = np.clip(np.floor((h_t - off) / (res * coarse)).astype(np.int64), 0, n_c - 1)
    h_pow = h_amp * tmap[h_ray, hb]

    # ---------------- point scatterers (persistent + this scan's precipitation clutter)
    pts, rcs, kind = prim.pts, prim.pts_rcs, prim.pts_kind
    if cond.volume_clutter_per_m2 > 0:
        n_v = rng.poisson(cond.volume_clutter_per_m2 * np.pi * 60.0 ** 2)
        rr = 60.0 * np.sqrt(rng.uniform(0.0004, 1, n_v))
        aa = rng.uniform(0, 2 * np.pi, n_v)
        vxy = mid[:2] + rr[:, None] * np.stack([np.cos(aa), np.sin(aa)], axis=1)
        pts = np.concatenate([pts, vxy])
        rcs = np.concatenate([rcs, rng.exponential(cond.volume_clutter_rcs, n_v)])
        kind = np.concatenate([kind, np.full(n_v, 3, np.int8)])
    if len(pts):
        ap, rp = _to_sensor(pts, mid)
        sel = rp < max_r + motion + 2
        pts, rcs, kind, ap = pts[sel], rcs[sel], kind[sel], ap[sel]
        j = np.floor(ap / dth_f + K / 2).astype(np.int64) % n_fine
        ap, rp = _to_sensor(pts, poses[j])  # re-project from the pose at that azimuth's time
        j = np.floor(ap / dth_f + K / 2).astype(np.int64) % n_fine
        ok = (rp > cfg.min_range_m) & (rp < max_r)
        pts = pts[ok]
        j, rp, rcs, kind = j[ok], rp[ok], rcs[ok], kind[ok]
        # aspect-dependent glint: a real scatterer's cross-section changes with the viewing direction
        bearing = np.arctan2(poses[j, 1] - pts[:, 1], poses[j, 0] - pts[:, 0])
        rcs = rcs * _aspect_gain(_point_ids(pts), bearing, cfg)
        rcs = np.where(kind == 1, rcs * cond.leaf_factor, rcs)
        if cfg.hard_point_gain != 1.0:
            rcs = np.where(kind == 0, rcs * cfg.hard_point_gain, rcs)
        rcs = np.where(kind == 2, rcs * cond.ground_factor
                       * _elevation_gain(rp, cfg, None if peak_f is None else peak_f[j]), rcs)
        # 1 m tolerance: a scatterer on a wall (façade detail) is not shadowed by the wall it sits on, even
        # when its sub-ray meets the wall a little earlier at grazing incidence
        pb = np.clip(np.floor((rp - 1.0 - off) / (res * coarse)).astype(np.int64), 0, n_c - 1)
        p_pow = rcs * tmap[j, pb]
        p_coh = kind == 0
    else:
        j = np.zeros(0, np.int64)
        rp = p_pow = np.zeros(0)
        p_coh = np.zeros(0, bool)

    # ---------------- impulses -> (A, R) target power
    all_ray = np.concatenate([h_ray, j]) // K
    all_r = np.concatenate([h_t, rp])
    all_p = np.concatenate([h_pow, p_pow])
    all_coh = np.concatenate([h_coh, p_coh])
    atten = 10 ** (-2 * cond.attenuation_db_per_km * all_r / 1e4)
    all_p = all_p * cfg.target_gain * (cfg.ref_range_m / np.maximum(all_r, 1.0)) ** cfg.range_exponent * atten
    # multipath ghosts: a fraction of the strongest returns reappear farther out along the same azimuth
    if len(all_p) and cfg.ghost_prob > 0:
        strong = np.nonzero(all_p > np.quantile(all_p, 0.995))[0]
        g = strong[rng.random(len(strong)) < cfg.ghost_prob]
        if len(g):
            all_ray = np.concatenate([all_ray, all_ray[g]])
            all_r = np.concatenate([all_r, all_r[g] + rng.uniform(3.0, 25.0, len(g))])
            all_p = np.concatenate([all_p, all_p[g] * 0.02])
            all_coh = np.concatenate([all_coh, np.zeros(len(g), bool)])  # multipath: diffuse
    fb = (all_r - off) / res
    okb = (fb >= 0) & (fb < n_r - 1)
    fb, all_ray, all_p, all_coh = fb[okb], all_ray[okb], all_p[okb], all_coh[okb]
    b0 = np.floor(fb).astype(np.int64)
    wb = fb - b0
    flat = np.concatenate([all_ray * n_r + b0, all_ray * n_r + b0 + 1])
    k_r, anchor_r, k_a = _kernels(cfg, res)
    pad = len(k_a) // 2

    def impulses_to_image(weight: np.ndarray) -> np.ndarray:
        wts = np.concatenate([all_p * weight * (1 - wb), all_p * weight * wb])
        target = np.bincount(flat, weights=wts, minlength=n_az * n_r).astype(np.float32).reshape(n_az, n_r)
        padded = np.concatenate([target[-pad:], target, target[:pad]], axis=0)
        return cv2.sepFilter2D(padded, cv2.CV_32F, k_r, k_a, anchor=(anchor_r, pad),
                               borderType=cv2.BORDER_CONSTANT)[pad:-pad]

    dom_w = np.where(all_coh, cfg.dominant_fraction, 0.0) if cfg.speckle_looks > 0 else np.zeros(len(all_p))
    blurred = impulses_to_image(1.0 - dom_w)  # distributed part: fully speckled
    dominant = impulses_to_image(dom_w) if np.any(dom_w > 0) else None

    # ---------------- diffuse ground, noise floor, near field
    ranges = (off + np.arange(n_r) * res).astype(np.float32)
    rr = np.maximum(ranges, 0.5)
    ground = (cfg.ground_level * cond.ground_factor * _elevation_gain(rr, cfg)
              * (cfg.ground_peak_m / np.maximum(rr, cfg.ground_peak_m)) ** 2.5).astype(np.float32)
    ground *= (10 ** (-2 * cond.attenuation_db_per_km * rr / 1e4)).astype(np.float32)
    # vehicle / radome self-returns: a plateau out to near_field_m, then a fast (0.2 m) roll-off
    near = (cfg.near_field_level * np.exp(-np.maximum(ranges - cfg.near_field_m, 0) / 0.2)).astype(np.float32)
    floor = cfg.noise_floor * 10 ** (cond.noise_floor_db / 10)
    # ground is shadowed like everything else: average the sub-ray transmission into azimuth cells
    tm = tmap.reshape(n_az, K, n_c).mean(axis=1)
    tm_full = cv2.resize(tm, (n_r, n_az), interpolation=cv2.INTER_NEAREST) if n_c != n_r else tm
    if peak_f is None:
        power = blurred + ground[None, :] * tm_full + (near + floor)[None, :]
    else:  # tilted vehicle: the ground profile per azimuth, with that azimuth's peak range
        pk = peak_f.reshape(n_az, K).mean(axis=1).astype(np.float32)[:, None]
        g2 = (cfg.ground_level * cond.ground_factor * _elevation_gain(rr[None, :], cfg, pk)
              * (pk / np.maximum(rr[None, :], pk)) ** 2.5).astype(np.float32)
        g2 *= (10 ** (-2 * cond.attenuation_db_per_km * rr / 1e4)).astype(np.float32)[None, :]
        power = blurred + g2 * tm_full + (near + floor)[None, :]

    if cfg.skirt_dbc is not None:
        power += _range_skirt(blurred if dominant is None else blurred + dominant, res, cfg)
    # beam-level jitter (own stream: the main stream's draws stay as they were without it)
    beam_rng = (np.random.default_rng([scan_seed, 0xBEA4])
                if cfg.azimuth_floor_db > 0 or cfg.azimuth_gain_db > 0 else None)
    if cfg.azimuth_floor_db > 0:
        jf = _azimuth_jitter(beam_rng, n_az, cfg.azimuth_floor_db, cfg.azimuth_gain_coupling) - np.float32(1.0)
        power += np.float32(floor) * jf[:, None]
    # interference streaks: a few azimuths saturated across range (another radar / the vehicle's own)
    n_st = rng.poisson(cfg.streak_rate)
    for _ in range(n_st):
        row = int(rng.integers(0, n_az))
        width = int(rng.integers(1, 3))
        lvl = 10 ** rng.uniform(1.5, 3.0)
        prof = (lvl * (10.0 / np.maximum(ranges, 10.0)) ** rng.uniform(1.0, 2.0)).astype(np.float32)
        for k in range(width):
            power[(row + k) % n_az] += prof

    if cfg.speckle_looks > 0:
        if dominant is None:
            power *= _speckle(rng, n_az, n_r, cfg)
        else:
            power = _rician(rng, n_az, n_r, cfg, dominant, power)
    elif dominant is not None:
        power += dominant
    if cfg.azimuth_gain_db > 0:
        power *= _azimuth_jitter(beam_rng, n_az, cfg.azimuth_gain_db, cfg.azimuth_gain_coupling)[:, None]
    np.maximum(power, 1e-12, out=power)
    # value = (10 log10 P - db_floor) / db_span, quantised to 8 bits (cv2.log: ~5x faster than np.log10)
    scale = np.float32(255.0 * 10.0 / np.log(10.0) / cfg.db_span)
    val = cv2.log(power) * scale - np.float32(255.0 * cfg.db_floor / cfg.db_span)
    np.clip(val, 0.0, 255.0, out=val)
    val = np.round(val) / np.float32(255.0)
    azimuths = np.arange(n_az) * dth
    return RadarScan(val.astype(np.float32), azimuths, az_t, res, off, preset=p.name)


def _range_skirt(target: np.ndarray, res: float, cfg: SensorConfig) -> np.ndarray:
    """(A, R) float32 power every return of ``target`` (A, R) spreads along its beam: ``target`` convolved along
    range with 10^(skirt_dbc / 10) (1 + |dr| / skirt_r0_m)^-skirt_exponent (circular-free, via FFT)."""
    n_r = target.shape[1]
    n_fft = 1 << int(np.ceil(np.log2(2 * n_r)))
    dr = np.minimum(np.arange(n_fft), n_fft - np.arange(n_fft)) * res
    kernel = 10 ** (cfg.skirt_dbc / 10) * (1.0 + dr / cfg.skirt_r0_m) ** (-cfg.skirt_exponent)
    kernel[n_r:n_fft - n_r + 1] = 0.0  # offsets beyond the beam: no wrap-around
    out = np.fft.irfft(np.fft.rfft(target, n_fft, axis=1) * np.fft.rfft(kernel)[None, :], n_fft, axis=1)
    return np.maximum(out[:, :n_r], 0.0).astype(np.float32)


def _azimuth_jitter(rng: np.random.Generator, n_az: int, std_db: float, coupling: float) -> np.ndarray:
    """(A,) float32 linear factor per azimuth: 10^(g / 10), g zero-mean Gaussian in dB with standard deviation
    ``std_db``, neighbouring azimuths coupled by ``coupling`` (``[c, 1, c]``, circular, rescaled)."""
    g = rng.standard_normal(n_az)
    g = (g + coupling * (np.roll(g, 1) + np.roll(g, -1))) / np.sqrt(1.0 + 2.0 * coupling * coupling)
    return (10.0 ** (std_db * g / 10.0)).astype(np.float32)


def _speckle(rng: np.random.Generator, n_az: int, n_r: int, cfg: SensorConfig) -> np.ndarray:
    """(A, R) float32 multiplicative speckle with mean 1, correlated along range and azimuth like real scans.

    The complex echo is drawn on a grid ``speckle_range_cell`` bins coarse in range, interpolated (the
    sensor's FFT bins oversample its range resolution) and smoothed over neighbouring azimuths (overlapping
    beams); the intensity |z|^2 is exponential (one look) per cell, summed over ``speckle_looks`` looks.
    """
    cell = cfg.speckle_range_cell
    n_c = n_r // cell + 2
    out = np.zeros((n_az, n_r), np.float32)
    looks = max(1, int(round(cfg.speckle_looks)))
    k_az = np.array([cfg.speckle_az_coupling, 1.0, cfg.speckle_az_coupling], np.float32)
    for _ in range(looks):
        for _part in range(2):
            g = rng.standard_normal((n_az, n_c), dtype=np.float32)
            g = cv2.filter2D(np.concatenate([g[-1:], g, g[:1]]), cv2.CV_32F, k_az[:, None])[1:-1]
            up = np.ascontiguousarray(cv2.resize(g, (n_c * cell, n_az), interpolation=cv2.INTER_CUBIC)[:, :n_r])
            cv2.accumulateSquare(up, out)
    out *= np.float32(1.0 / cv2.mean(out)[0])
    return out


def _speckle_field(rng: np.random.Generator, n_az: int, n_r: int, cfg: SensorConfig) -> np.ndarray:
    """(A, R) float32 zero-mean Gaussian field, correlated like ``_speckle``'s (one quadrature component)."""
    cell = cfg.speckle_range_cell
    n_c = n_r // cell + 2
    k_az = np.array([cfg.speckle_az_coupling, 1.0, cfg.speckle_az_coupling], np.float32)
    g = rng.standard_normal((n_az, n_c), dtype=np.float32)
    g = cv2.filter2D(np.concatenate([g[-1:], g, g[:1]]), cv2.CV_32F, k_az[:, None])[1:-1]
    return np.ascontiguousarray(cv2.resize(g, (n_c * cell, n_az), interpolation=cv2.INTER_CUBIC)[:, :n_r])


def _rician(rng: np.random.Generator, n_az: int, n_r: int, cfg: SensorConfig, dominant: np.ndarray,
            diffuse: np.ndarray) -> np.ndarray:
    """(A, R) float32 intensity |sqrt(D) + sqrt(P) z|^2 averaged over looks: a steady dominant scatterer of
    power D plus fully developed speckle of mean power P (z unit complex Gaussian, correlated like
    ``_speckle``). Mean intensity D + P, as without speckle."""
    looks = max(1, int(round(cfg.speckle_looks)))
    a = np.sqrt(dominant)
    b = np.sqrt(diffuse)
    out = np.zeros((n_az, n_r), np.float32)
    for _ in range(looks):
        re, im = _speckle_field(rng, n_az, n_r, cfg), _speckle_field(rng, n_az, n_r, cfg)
        norm = np.float32(1.0 / np.sqrt(np.mean(re * re + im * im)))
        re *= norm
        im *= norm
        out += (a + b * re) ** 2 + (b * im) ** 2
    return out / np.float32(looks)


def scan_seed(traversal_seed: int, scan_index: int) -> int:
    """Seed of one scan's noise, from the traversal seed and the scan index (renders alone identically)."""
    return stable_seed(traversal_seed, "scan", scan_index)
