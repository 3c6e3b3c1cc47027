"""Benchmark results on disk: ``results.json`` and ``results.md`` (tables laid out like the paper's)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["write_results", "results_markdown", "METRIC_COLUMNS"]

#: (key in results.json, column header, format) of the paper's per-sequence columns.
METRIC_COLUMNS = (("recall@1", "Recall@1 (%)", "{:.2f}"), ("f1max", "F1max (%)", "{:.2f}"),
                  ("sr", "SR (%)", "{:.2f}"), ("e_r_deg", "ê_r (°)", "{:.2f}"), ("e_t_m", "ê_t (m)", "{:.2f}"))


def _fmt(v: Any, fmt: str) -> str:
    return "–" if v is None else fmt.format(v)


def _best(rows: dict[str, dict[str, Any]], key: str) -> set[str]:
    vals = {m: r.get(key) for m, r in rows.items() if r.get(key) is not None}
    if not vals:
        return set()
    target = max(vals.values()) if key in ("recall@1", "f1max", "sr") else min(vals.values())
    return {m for m, v in vals.items() if abs(v - target) < 1e-9}


def results_markdown(results: dict[str, Any]) -> str:
    """Markdown like the paper's tables: methods as rows, per-sequence Recall@1 / F1max / SR / ê_r / ê_t
    column groups, best values in bold; then time per query, rotation stress and stage timings."""
    lines = [f"# `reradar bench` results — suite `{results.get('suite')}`", ""]
    radius = results.get("settings", {}).get("radius_m")
    lines.append(f"Correct retrieval within {radius} m; Recall@1 and SR over all queries; SR: translation < "
                 f"{radius} m and rotation < 10° (heading-only methods ReFeree, RaPlace: correct retrieval and "
                 "rotation < 10°); ê_r, ê_t over successes; – = not applicable; ms/query = features + "
                 "retrieval (+ verification) per query on this machine.")
    lines.append("")
    seqs = results.get("sequences", {})
    pairs = results.get("settings", {}).get("pairs", {})
    for seq in seqs:
        p = pairs.get(seq)
        if p:
            rev = next((r.get("n_with_revisit") for r in seqs[seq].values() if "n_with_revisit" in r), None)
            note = (f" ({rev} with a database keyframe within {radius} m: Recall@1 and SR are at most "
                    f"{100.0 * rev / max(p['n_query'], 1):.2f}%)") if rev is not None and rev < p["n_query"] else ""
            lines.append(f"- `{seq}`: {p['n_query']} queries{note} against database `{p['database']}` "
                         f"({p['n_database']} keyframes)")
    lines.append("")
    methods: list[str] = []
    for rows in seqs.values():
        methods += [m for m in rows if m not in methods]
    head = "| Method | " + " | ".join(f"{seq}: {h}" for seq in seqs for _, h, _ in METRIC_COLUMNS) + " |"
    lines += [head, "|" + "---|" * (1 + len(seqs) * len(METRIC_COLUMNS))]
    best = {(seq, k): _best(rows, k) for seq, rows in seqs.items() for k, _, _ in METRIC_COLUMNS}
    for m in methods:
        cells = []
        for seq, rows in seqs.items():
            r = rows.get(m, {})
            for k, _, fmt in METRIC_COLUMNS:
                c = _fmt(r.get(k), fmt)
                cells.append(f"**{c}**" if m in best[(seq, k)] and c != "–" else c)
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    lines.append("")
    lines += ["Time per query (features + retrieval + verification, ms, this machine):", "",
              "| Method | " + " | ".join(seqs) + " |", "|" + "---|" * (1 + len(seqs))]
    for m in methods:
        lines.append(f"| {m} | " + " | ".join(_fmt(rows.get(m, {}).get("ms_per_query"), "{:.1f}")
                                             for rows in seqs.values()) + " |")
    lines.append("")
    posed = [m for m in methods if any(rows.get(m, {}).get("wrong_pose_pct") is not None for rows in seqs.values())]
    if posed:
        lines += ["Wrong poses (% of queries answered `localized` with a pose that misses the SR rule; methods "
                  "that report a full pose):", "", "| Method | " + " | ".join(seqs) + " |", "|" + "---|" * (1 + len(seqs))]
        for m in posed:
            lines.append(f"| {m} | " + " | ".join(_fmt(rows.get(m, {}).get("wrong_pose_pct"), "{:.2f}")
                                                 for rows in seqs.values()) + " |")
        lines.append("")
    stress = results.get("rotation_stress")
    if stress:
        lines += ["### Rotation stress (random heading offset added to every query scan)", ""]
        seqs = list(stress)
        lines.append("| Method | " + " | ".join(f"{s}: Recall@1 → rotated (Δ points)" for s in seqs) + " |")
        lines.append("|" + "---|" * (len(seqs) + 1))
        methods = list(next(iter(stress.values())).keys())
        for m in methods:
            cells = []
            for s in seqs:
                r = stress[s].get(m)
                cells.append("–" if r is None else
                             f"{r['recall@1']:.2f} → {r['recall@1_rotated']:.2f} (Δ {-r['drop']:+.2f})")
            lines.append(f"| {m} | " + " | ".join(cells) + " |")
        lines.append("")
    timing = results.get("timing")
    if timing:
        lines += [f"### Stage timings ({timing.get('model')}, {timing.get('n_scans')} scans, "
                  f"{timing.get('threads')} thread(s), database {timing.get('n_database')} keyframes, "
                  f"1-min load average {timing.get('load_average_1min', float('nan')):.1f} on "
                  f"{results.get('settings', {}).get('cpu_count')} cores)", "",
                  "| Stage | mean ms | median ms |", "|---|---|---|"]
        for stage, v in timing["stages_ms"].items():
            lines.append(f"| {stage} | {v['mean']:.2f} | {v['median']:.2f} |")
        lines.append("")
    return "\n".join(lines)


def write_results(results: dict[str, Any], out_dir: Path) -> tuple[Path, Path]:
    """Write ``out_dir/results.json`` and ``out_dir/results.md``; returns both paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    jpath, mpath = out_dir / "results.json", out_dir / "results.md"
    jpath.write_text(json.dumps(results, indent=2, sort_keys=False) + "\n")
    mpath.write_text(results_markdown(results) + "\n")
    return jpath, mpath
