"""Real-vs-simulated scan statistics side by side (``reradar sim-report``) and preview images."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from reradar_core.errors import DatasetError
from reradar_core.geometry.cartesian import CartesianConfig, polar_to_cartesian
from reradar_core.io.datasets import detect_layout, load_sequence
from reradar_core.io.scan import RadarScan, read_navtech_png
from reradar_core.sim.stats import RANGE_BANDS_M, ScanStats, scan_statistics, summarize

__all__ = ["collect_scans", "compare_table", "save_preview", "folder_statistics"]


def collect_scans(folder: str | Path, limit: int = 12, preset: str | None = None) -> list[RadarScan]:
    """Up to ``limit`` scans, evenly spaced, from a sequence folder (any layout) or a folder of PNGs."""
    folder = Path(folder)
    try:
        detect_layout(folder)
        seq = load_sequence(folder, preset=preset)
        idx = np.linspace(0, len(seq) - 1, min(limit, len(seq))).round().astype(int)
        return [seq.load_scan(int(i)) for i in np.unique(idx)]
    except DatasetError:
        pngs = sorted(folder.glob("*.png")) or sorted((folder / "radar").glob("*.png"))
        if not pngs:
            raise DatasetError(f"{folder}: no radar sequence or *.png scans found") from None
        idx = np.unique(np.linspace(0, len(pngs) - 1, min(limit, len(pngs))).round().astype(int))
        return [read_navtech_png(pngs[int(i)], preset) for i in idx]


def folder_statistics(folder: str | Path, limit: int = 12, preset: str | None = None) -> dict:
    """Summary statistics of up to ``limit`` scans of ``folder``; ``radar_preset`` names the preset they were read
    with (``preset``, or the folder's own), so a comparison of different radars can say so."""
    scans = collect_scans(folder, limit, preset)
    stats: list[ScanStats] = [scan_statistics(s) for s in scans]
    out = summarize(stats)
    out["radar_preset"] = scans[0].preset if scans else None
    out["num_scans"] = len(stats)
    out["keypoints_min"] = float(min(s.keypoints for s in stats))
    out["keypoints_max"] = float(max(s.keypoints for s in stats))
    return out


def compare_table(columns: dict[str, dict]) -> str:
    """A Markdown table of statistics, one column per source (e.g. ``{"real": ..., "sim clear": ...}``)."""
    names = list(columns)
    rows = [
        ("radar preset", "radar_preset", "{}"),
        ("scans", "num_scans", "{:.0f}"),
        ("mean power", "mean", "{:.4f}"),
        ("median", "p50", "{:.3f}"),
        ("90th percentile", "p90", "{:.3f}"),
        ("99th percentile", "p99", "{:.3f}"),
        ("99.9th percentile", "p999", "{:.3f}"),
        ("fraction of bins = 0", "frac_zero", "{:.3f}"),
        ("fraction above noise floor", "frac_above_floor", "{:.3f}"),
        ("Cen 2018 keypoints / scan", "keypoints", "{:.0f}"),
        ("keypoints min-max", None, ""),
    ]
    lines = ["| statistic | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for label, key, fmt in rows:
        cells = []
        for n in names:
            c = columns[n]
            if key is None:
                cells.append(f"{c['keypoints_min']:.0f}-{c['keypoints_max']:.0f}")
            else:
                cells.append(fmt.format(c.get(key, "–")))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    for b, (lo, hi) in enumerate(RANGE_BANDS_M):
        lines.append(f"| mean power {lo:.0f}-{hi:.0f} m | " + " | ".join(
            f"{columns[n]['band_mean'][b]:.3f}" for n in names) + " |")
    edges = np.linspace(0, 1, 17)
    for b in range(6):
        lines.append(f"| histogram [{edges[b]:.3f}, {edges[b + 1]:.3f}) | " + " | ".join(
            f"{columns[n]['hist'][b]:.3f}" for n in names) + " |")
    lines.append("| histogram >= 0.375 | " + " | ".join(
        f"{sum(columns[n]['hist'][6:]):.4f}" for n in names) + " |")
    return "\n".join(lines)


def save_preview(scan: RadarScan, path_prefix: str | Path, max_range_m: float = 100.0, gain: float = 2.0) -> list[Path]:
    """Write ``<prefix>_polar.png`` (first ``max_range_m``) and ``<prefix>_cart.png`` (±max_range_m)."""
    prefix = Path(path_prefix)
    prefix.parent.mkdir(parents=True, exist_ok=True)
    n_bins = int(np.searchsorted(scan.ranges_m, max_range_m))
    polar = np.clip(scan.power[:, :n_bins] * 255 * gain, 0, 255).astype(np.uint8)
    polar = cv2.resize(polar, (800, 400), interpolation=cv2.INTER_AREA)
    cfg = CartesianConfig(801, 2 * max_range_m / 801)
    cart = np.clip(polar_to_cartesian(scan, cfg) * 255 * gain, 0, 255).astype(np.uint8)
    out = [prefix.with_name(prefix.name + "_polar.png"), prefix.with_name(prefix.name + "_cart.png")]
    cv2.imwrite(str(out[0]), polar)
    cv2.imwrite(str(out[1]), cart)
    return out
