"""Benchmark results on disk: ``results.json`` and ``results.md`` (tables laid out like the paper's)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["write_results", "results_markdown", "signed_points", "method_labels", "METRIC_COLUMNS", "QUERY_KIND_COLUMNS",
           "REJECTION_NOTE", "DESCRIPTOR_NOTE"]

#: (key in results.json, column header, format) of the paper's per-sequence columns (Recall@1 and SR over
#: revisit queries, the headline).
METRIC_COLUMNS = (("recall@1", "Recall@1 (%)", "{:.2f}"), ("f1max", "F1max (%)", "{:.2f}"),
                  ("sr", "SR (%)", "{:.2f}"), ("e_r_deg", "ê_r (°)", "{:.2f}"), ("e_t_m", "ê_t (m)", "{:.2f}"))
#: Columns of the second table: all queries, and the queries without a match (rejection figures).
QUERY_KIND_COLUMNS = (("recall@1_ci95", "Recall@1, 95 % interval (%)", "{0[0]:.1f}–{0[1]:.1f}"),
                      ("recall@1_all", "Recall@1 all (%)", "{:.2f}"), ("sr_all", "SR all (%)", "{:.2f}"),
                      ("recall@1_descriptor", "Recall@1, global descriptor alone, revisits (%)", "{:.2f}"),
                      ("correct_rejection_pct", "correct rejection (%)", "{:.2f}"),
                      ("wrong_pose_no_match_pct", "wrong pose, no match (%)", "{:.2f}"))

#: How the results define "rejected" for each kind of method (printed under the tables, docs/BENCHMARKS.md).
REJECTION_NOTE = ("Rejected: ReRadar (methods with a full pose) rejects a query when it answers `not_localized` "
                  "(fewer of its landmarks align than the floor, an ambiguous pose, or a confidence below the bar; "
                  "floor and bar are fitted on the training splits with the confidence model, docs/MODEL.md); the "
                  "retrieval-only and heading-only baselines (RingKey, RaPlace, RadVLAD, ResNet18-NetVLAD, ReFeree) "
                  "always answer: no distance threshold is chosen (one tuned on the query sequence would be a "
                  "defect), so their rejection figures are – (not applicable), and every answer they give to a query "
                  "without a match is a wrong place.")

#: What "global descriptor alone" reads for each kind of ReRadar row (printed under the tables).
DESCRIPTOR_NOTE = ("Global descriptor alone: the place of the nearest map descriptor, before any landmark screen "
                   "(ReRadar rows only; the other methods' Recall@1 already is their descriptor's). With the far view "
                   "(`+far`, `+dense`) it is the two-view reading: the far view's descriptor for a query whose near view "
                   "holds fewer landmarks than the far view's `sparse_landmarks` (512), else the near view's "
                   "(docs/MODEL.md, \"The two-view descriptor\").")


def _fmt(v: Any, fmt: str) -> str:
    return "–" if v is None else fmt.format(v)


def _best(rows: dict[str, dict[str, Any]], key: str) -> set[str]:
    if key.endswith("_ci95"):  # an interval is not ranked
        return set()
    vals = {m: r.get(key) for m, r in rows.items() if r.get(key) is not None}
    if not vals:
        return set()
    higher = ("recall@1", "f1max", "sr", "recall@1_all", "sr_all", "correct_rejection_pct", "recall@1_descriptor")
    target = max(vals.values()) if key in higher else min(vals.values())
    best = {m for m, v in vals.items() if abs(v - target) < 1e-9}
    # every method tied (e.g. 0.00 % for all on a run where no query has a match): no method is best
    return set() if len(vals) > 1 and len(best) == len(vals) else best


def method_labels(settings: dict[str, Any]) -> dict[str, str]:
    """Row label of each method in results.md: its name, and for a ReRadar method named otherwise than the model
    it runs (``settings["method_models"]``: ``ours`` runs the default model) the model too:
    ``ours (our-3-boreas-w05)``."""
    labels = {}
    for m, model in (settings.get("method_models") or {}).items():
        labels[m] = f"{m} ({model})" if model and str(model) != m else m
    return labels


def _table(seqs: dict[str, dict[str, Any]], methods: list[str],
           columns: tuple[tuple[str, str, str], ...], labels: dict[str, str] | None = None) -> list[str]:
    """Methods as rows (``labels``: row label by method, default the name), per-sequence column groups, best
    value per column in bold."""
    labels = labels or {}
    head = "| Method | " + " | ".join(f"{seq}: {h}" for seq in seqs for _, h, _ in columns) + " |"
    lines = [head, "|" + "---|" * (1 + len(seqs) * len(columns))]
    best = {(seq, k): _best(rows, k) for seq, rows in seqs.items() for k, _, _ in columns}
    for m in methods:
        cells = []
        for seq, rows in seqs.items():
            r = rows.get(m, {})
            for k, _, fmt in columns:
                c = _fmt(r.get(k), fmt)
                cells.append(f"**{c}**" if m in best[(seq, k)] and c != "–" else c)
        lines.append(f"| {labels.get(m, m)} | " + " | ".join(cells) + " |")
    return lines


def signed_points(value: float) -> str:
    """A change in percentage points with its sign, two decimals; one that rounds to zero is ``0.00`` (never
    ``-0.00`` or ``+0.00``)."""
    return "0.00" if abs(value) < 0.005 else f"{value:+.2f}"


def results_markdown(results: dict[str, Any]) -> str:
    """Markdown like the paper's tables: methods as rows, per-sequence Recall@1 / F1max / SR / ê_r / ê_t
    column groups, best values in bold; then time per query, rotation stress and stage timings."""
    settings = results.get("settings", {})
    folder = settings.get("database_folder")  # a run on recorded folders names no suite
    source = f"database folder `{Path(folder).name}`" if folder else f"suite `{results.get('suite')}`"
    lines = [f"# `reradar bench` results — {source}", ""]
    labels = method_labels(settings)
    radius = settings.get("radius_m")
    lines.append(f"Correct retrieval within {radius} m. **Recall@1 and SR are over the revisit queries** (those "
                 f"with a database keyframe within {radius} m); the same over all queries (the paper's GT) and "
                 f"the rejection figures on queries without a match are in the second table. SR: translation < "
                 f"{radius} m and rotation < 10° (heading-only methods ReFeree, raplace-nodc: correct retrieval and "
                 "rotation < 10°); ê_r, ê_t over successes; F1max by the RaPlace protocol over all queries; "
                 "– = not applicable; ms/query = features + retrieval (+ verification) per query on this machine.")
    lines.append("")
    for name, p in settings.get("pairs", {}).items():
        split = p.get("split")
        if split:
            lines.append(f"Single-session split `{name}`: sequence `{split.get('sequence')}` ({split.get('n_scans')} "
                         f"scans) cut at `--split-at {split.get('spec')}` = scan index {split.get('index')} "
                         f"(timestamp {split.get('timestamp_us')} µs): database = scans before it, queries = "
                         "scans from it on (indices before subsampling).")
            lines.append("")
    if settings.get("every_note"):
        lines.append(f"Frame spacing: {settings['every_note']}.")
        lines.append("")
    if settings.get("network_runtime"):
        ran = ", ".join(f"{name} in {rt}" for name, rt in settings["network_runtime"].items())
        lines.append(f"Descriptor network: {ran} (`RERADAR_NETWORK_RUNTIME`; onnx = ONNX Runtime).")
        lines.append("")
    seqs = results.get("sequences", {})
    pairs = settings.get("pairs", {})
    for seq in seqs:
        p = pairs.get(seq)
        if p:
            row: dict[str, Any] = next((r for r in seqs[seq].values() if "n_queries" in r), {})
            rev = row.get("n_revisit", row.get("n_with_revisit"))
            kinds = (f": {rev} revisit {'query' if rev == 1 else 'queries'}, {p['n_query'] - rev} without a "
                     f"database keyframe within {radius} m") if rev is not None else ""
            lines.append(f"- `{seq}`: {p['n_query']} queries{kinds}; database `{p['database']}` "
                         f"({p['n_database']} keyframes)")
    lines.append("")
    methods: list[str] = []
    for rows in seqs.values():
        methods += [m for m in rows if m not in methods]
    lines += _table(seqs, methods, METRIC_COLUMNS, labels)
    lines.append("")
    lines += ["All queries, and queries without a match (correct rejection = rejected / no-match queries; wrong "
              "pose = answered with a pose that misses the SR rule / no-match queries):", ""]
    lines += _table(seqs, methods, QUERY_KIND_COLUMNS, labels)
    lines += ["", REJECTION_NOTE, ""]
    if any(r.get("recall@1_descriptor") is not None for rows in seqs.values() for r in rows.values()):
        lines += [DESCRIPTOR_NOTE, ""]
    counted = [m for m in methods if any(rows.get(m, {}).get("n_rejected_no_match") is not None
                                         for rows in seqs.values())]
    if counted:
        lines += ["Counts per kind of query (methods that can reject): revisit queries rejected / answered with a "
                  "wrong pose; no-match queries rejected / wrong pose / correct pose.", "",
                  "| Method | " + " | ".join(seqs) + " |", "|" + "---|" * (1 + len(seqs))]
        for m in counted:
            cells = []
            for rows in seqs.values():
                r = rows.get(m, {})
                if r.get("n_rejected_no_match") is None:
                    cells.append("–")
                    continue
                cells.append(f"{r['n_rejected_revisit']} / {r['n_wrong_pose_revisit']} of {r['n_revisit']}; "
                             f"{r['n_rejected_no_match']} / {r['n_wrong_pose_no_match']} / "
                             f"{r['n_correct_pose_no_match']} of {r['n_no_match']}")
            lines.append(f"| {labels.get(m, m)} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += ["Time per query (features + retrieval + verification, ms, this machine):", "",
              "| Method | " + " | ".join(seqs) + " |", "|" + "---|" * (1 + len(seqs))]
    for m in methods:
        lines.append(f"| {labels.get(m, m)} | " + " | ".join(_fmt(rows.get(m, {}).get("ms_per_query"), "{:.1f}")
                                             for rows in seqs.values()) + " |")
    lines.append("")
    posed = [m for m in methods if any(rows.get(m, {}).get("wrong_pose_pct") is not None for rows in seqs.values())]
    if posed:
        lines += ["Wrong poses (% of queries answered `localized` with a pose that misses the SR rule; methods "
                  "that report a full pose):", "", "| Method | " + " | ".join(seqs) + " |", "|" + "---|" * (1 + len(seqs))]
        for m in posed:
            lines.append(f"| {labels.get(m, m)} | " + " | ".join(_fmt(rows.get(m, {}).get("wrong_pose_pct"), "{:.2f}")
                                                 for rows in seqs.values()) + " |")
        lines.append("")
    covs = [m for m in methods if any(rows.get(m, {}).get("pose_covariance") for rows in seqs.values())]
    if covs:
        lines += ["Pose covariance (successful answers with one): how well it describes their errors. NEES = mean "
                  "e^T C^-1 e (3 when calibrated); inside = % of errors within its 50 / 95 / 99 % ellipsoid; RMS error "
                  "(predicted by the covariances):", "", "| Method | sequence | answers | NEES | inside 50 / 95 / 99 % | "
                  "position RMS m | heading RMS ° |", "|---|---|---|---|---|---|---|"]
        for m in covs:
            for seq, rows in seqs.items():
                c = rows.get(m, {}).get("pose_covariance")
                if not c:
                    continue
                lines.append(f"| {labels.get(m, m)} | {seq} | {c['n']} | {c['nees']:.2f} | {c['inside_50_pct']:.1f} / "
                             f"{c['inside_95_pct']:.1f} / {c['inside_99_pct']:.1f} | {c['rms_position_m']:.3f} "
                             f"({c['predicted_rms_position_m']:.3f}) | {c['rms_heading_deg']:.3f} "
                             f"({c['predicted_rms_heading_deg']:.3f}) |")
        lines.append("")
    stress = results.get("rotation_stress")
    if stress:
        lines += ["### Rotation stress (random heading offset added to every query scan; Recall@1 over the "
                  "revisit queries among them)", ""]
        seqs = list(stress)
        lines.append("| Method | " + " | ".join(f"{s}: Recall@1 → rotated (Δ points)" for s in seqs) + " |")
        lines.append("|" + "---|" * (len(seqs) + 1))
        methods = list(next(iter(stress.values())).keys())
        for m in methods:
            cells = []
            for s in seqs:
                r = stress[s].get(m)
                cells.append("–" if r is None or r.get("drop") is None else
                             f"{r['recall@1']:.2f} → {r['recall@1_rotated']:.2f} (Δ {signed_points(-r['drop'])})")
            lines.append(f"| {labels.get(m, m)} | " + " | ".join(cells) + " |")
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
