"""Figures from a benchmark run (PNG): precision-recall curves, trajectory retrieval links, rotation-stress
bars and the yaw-consistency curve."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

from reradar_core.baselines import BASELINES  # noqa: E402
from reradar_core.benchmark.metrics import pr_curve  # noqa: E402

__all__ = ["plot_pr_curves", "plot_trajectory_links", "plot_rotation_stress", "plot_yaw_consistency",
           "is_ours", "make_all_plots", "rejected_queries"]

_DPI = 90


def is_ours(method: str) -> bool:
    return method not in BASELINES


def _load(per_query: Path, seq: str, method: str) -> dict[str, np.ndarray] | None:
    p = per_query / seq / f"{method}.npz"
    if not p.is_file():
        return None
    with np.load(p) as z:
        return {k: z[k] for k in z.files}


def plot_pr_curves(results: dict[str, Any], per_query: Path, seq: str, path: Path) -> Path:
    """Precision-recall curve of every method on one sequence (threshold on the top-1 distance)."""
    fig, ax = plt.subplots(figsize=(5.2, 4.2))
    for m, r in results["sequences"][seq].items():
        d = _load(per_query, seq, m)
        if d is None:
            continue
        p, rc = pr_curve(d["distance"], d["correct"], d["positive"])
        f1 = "–" if r.get("f1max") is None else f"{r['f1max']:.1f}"  # None: no revisit query
        ax.plot(rc, p, lw=2.2 if is_ours(m) else 1.3, ls="-" if is_ours(m) else "--", label=f"{m} (F1max {f1})")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1.01)
    ax.set_ylim(0, 1.01)
    ax.set_title(f"Precision-recall — {seq}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def strongest(results: dict[str, Any], seq: str, ours: bool) -> str | None:
    """The method (ours or a baseline) with the highest Recall@1 on ``seq``."""
    rows = {m: r for m, r in results["sequences"][seq].items() if is_ours(m) == ours}
    if not rows:
        return None
    return max(rows, key=lambda m: (rows[m]["recall@1"] or 0.0, rows[m]["f1max"] or 0.0))


def rejected_queries(row: dict[str, Any], est_pose: np.ndarray) -> np.ndarray:
    """(Q,) bool: the queries ``row``'s method rejected (answered ``not_localized``: no pose).

    Only a method with a rejection rule (results ``rejection`` not None: ReRadar) rejects; a retrieval-only
    baseline has no pose either but answers every query, so none of its queries is rejected.
    """
    est = np.asarray(est_pose, dtype=np.float64).reshape(-1, 3)
    if row.get("rejection") is None:
        return np.zeros(len(est), dtype=bool)
    return ~np.isfinite(est[:, 0])


def plot_trajectory_links(results: dict[str, Any], per_query: Path, seq: str, path: Path,
                          methods: list[str] | None = None) -> Path:
    """Database (solid) and query (dashed) paths with each answered query's retrieval link, green = correct,
    red = wrong; a query the method rejected (ReRadar's ``not_localized``) gets no link but a grey cross (one
    panel per method, default: the best of ours and the strongest baseline)."""
    if methods is None:
        methods = [m for m in (strongest(results, seq, True), strongest(results, seq, False)) if m]
    fig, axes = plt.subplots(1, len(methods), figsize=(5.4 * len(methods), 5.0), squeeze=False)
    for ax, m in zip(axes[0], methods, strict=True):
        d = _load(per_query, seq, m)
        if d is None:
            continue
        row = results["sequences"][seq][m]
        origin = d["db_xy"].min(axis=0)  # UTM-sized coordinates are unreadable on the axes
        q, db = d["query_xy"] - origin, d["db_xy"] - origin
        ax.plot(db[:, 0], db[:, 1], "k-", lw=1.2, label="database")
        ax.plot(q[:, 0], q[:, 1], "k--", lw=1.0, label="query")
        rejected = rejected_queries(row, d["est_pose"])
        shown = ~rejected
        segs = np.stack([q[shown], db[d["retrieved"][shown]]], axis=1)
        colors = np.where(d["correct"][shown, None], [[0.1, 0.65, 0.2, 0.8]], [[0.85, 0.1, 0.1, 0.8]])
        ax.add_collection(LineCollection(segs, colors=colors, linewidths=0.8))
        ax.scatter(q[shown, 0], q[shown, 1], s=6, c=colors, zorder=3)  # short correct links are hard to see
        if rejected.any():
            ax.scatter(q[rejected, 0], q[rejected, 1], s=14, marker="x", c=[[0.45, 0.45, 0.45, 0.9]], zorder=3,
                       linewidths=0.8, label=f"rejected (no answer): {int(rejected.sum())}")
        r1 = row["recall@1"]
        n_rev = int(row.get("n_revisit", len(q)))
        r1_txt = "–" if r1 is None else f"{r1:.1f}%"
        ax.set_title(f"{m}: Recall@1 {r1_txt} ({int(d['correct'].sum())}/{n_rev} revisit queries)", fontsize=9)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"x − {origin[0]:.0f} [m]")
        ax.set_ylabel(f"y − {origin[1]:.0f} [m]")
        ax.legend(fontsize=7, loc="best")
    fig.suptitle(f"Retrieval links — {seq} (green: correct, red: wrong, grey cross: rejected)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def plot_rotation_stress(results: dict[str, Any], path: Path) -> Path | None:
    """Grouped bars: Recall@1 with and without a random heading offset, per method, averaged over sequences."""
    stress = results.get("rotation_stress")
    if not stress:
        return None
    methods = list(next(iter(stress.values())).keys())
    def mean(key: str, m: str) -> float:
        vals = [stress[s][m][key] for s in stress if stress[s][m][key] is not None]
        return float(np.mean(vals)) if vals else 0.0

    base = [mean("recall@1", m) for m in methods]
    rot = [mean("recall@1_rotated", m) for m in methods]
    x = np.arange(len(methods))
    fig, ax = plt.subplots(figsize=(max(5.0, 0.9 * len(methods) + 2), 3.8))
    ax.bar(x - 0.2, base, 0.4, label="original heading")
    ax.bar(x + 0.2, rot, 0.4, label="random heading offset")
    ax.set_xticks(x, methods, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("Recall@1 (%)")
    ax.set_ylim(0, 105)
    ax.set_title("Rotation stress (mean over sequences)")
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def plot_yaw_consistency(curves: dict[str, tuple[np.ndarray, np.ndarray]], path: Path) -> Path:
    """Mean cosine consistency S(theta) of aligned F' under controlled yaw rotations, one curve per model."""
    fig, ax = plt.subplots(figsize=(5.2, 3.8))
    for name, (ang, s) in curves.items():
        ax.plot(ang, s, marker="o", ms=3, label=name)
    ax.set_xlabel("yaw rotation θ (°)")
    ax.set_ylabel("mean cosine consistency")
    ax.set_xticks(np.arange(0, 361, 45))
    ax.set_ylim(min(0.5, min(float(np.min(s)) for _, s in curves.values()) - 0.05), 1.01)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Yaw consistency of F'")
    fig.tight_layout()
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def make_all_plots(results: dict[str, Any], out_dir: Path) -> list[Path]:
    """Write ``pr_<seq>.png``, ``trajectory_<seq>.png`` and ``rotation_stress.png`` into ``out_dir``."""
    out_dir = Path(out_dir)
    per_query = out_dir / "per_query"
    paths: list[Path] = []
    for seq in results["sequences"]:
        paths.append(plot_pr_curves(results, per_query, seq, out_dir / f"pr_{seq}.png"))
        paths.append(plot_trajectory_links(results, per_query, seq, out_dir / f"trajectory_{seq}.png"))
    p = plot_rotation_stress(results, out_dir / "rotation_stress.png")
    if p:
        paths.append(p)
    return paths
