"""Prometheus text-format metrics (counters and histograms) without an extra dependency."""

from __future__ import annotations

import bisect
import threading
from collections import defaultdict

__all__ = ["Metrics", "LATENCY_BUCKETS_S"]

#: Histogram bucket upper bounds, seconds.
LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0, 2.5, 5.0, 10.0)

LabelKey = tuple[tuple[str, str], ...]


def _labels(key: LabelKey) -> str:
    if not key:
        return ""
    esc = [(k, v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")) for k, v in key]
    return "{" + ",".join(f'{k}="{v}"' for k, v in esc) + "}"


class _Histogram:
    def __init__(self) -> None:
        self.counts = [0] * (len(LATENCY_BUCKETS_S) + 1)
        self.total = 0.0
        self.n = 0

    def observe(self, value: float) -> None:
        self.counts[bisect.bisect_left(LATENCY_BUCKETS_S, value)] += 1
        self.total += value
        self.n += 1


class Metrics:
    """Thread-safe registry of the service's metrics.

    - ``reradar_http_requests_total{method,route,status}`` counter
    - ``reradar_http_request_duration_seconds{method,route}`` histogram
    - ``reradar_stage_duration_seconds{stage}`` histogram (decode, extract, retrieve, read, match, ransac)
    - ``reradar_localizations_total{status}`` counter
    - gauges set by the app: maps loaded, scan cache entries
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counters: dict[str, dict[LabelKey, float]] = defaultdict(dict)
        self._hists: dict[str, dict[LabelKey, _Histogram]] = defaultdict(dict)
        self._gauges: dict[str, dict[LabelKey, float]] = defaultdict(dict)
        self._help: dict[str, tuple[str, str]] = {
            "reradar_http_requests_total": ("counter", "HTTP requests by method, route template and status."),
            "reradar_http_request_duration_seconds": ("histogram", "HTTP request latency, seconds."),
            "reradar_stage_duration_seconds": ("histogram", "Pipeline stage latency, seconds."),
            "reradar_localizations_total": ("counter", "Localization outcomes by status."),
            "reradar_maps_loaded": ("gauge", "Maps ready for queries."),
            "reradar_scan_cache_entries": ("gauge", "Uploaded scans held in the feature cache."),
        }

    def inc(self, name: str, value: float = 1.0, **labels: str) -> None:
        key = tuple(sorted(labels.items()))
        with self._lock:
            self._counters[name][key] = self._counters[name].get(key, 0.0) + value

    def observe(self, name: str, seconds: float, **labels: str) -> None:
        key = tuple(sorted(labels.items()))
        with self._lock:
            self._hists[name].setdefault(key, _Histogram()).observe(seconds)

    def set_gauge(self, name: str, value: float, **labels: str) -> None:
        with self._lock:
            self._gauges[name][tuple(sorted(labels.items()))] = value

    def observe_stages(self, timings_ms: dict[str, float]) -> None:
        for stage, ms in timings_ms.items():
            if stage.endswith("_ms") and stage != "total_ms":
                self.observe("reradar_stage_duration_seconds", ms / 1e3, stage=stage[:-3])

    def render(self) -> str:
        """Prometheus text exposition format 0.0.4."""
        lines: list[str] = []
        with self._lock:
            names = sorted(set(self._counters) | set(self._hists) | set(self._gauges) | set(self._help))
            for name in names:
                kind, help_text = self._help.get(name, ("untyped", name))
                lines.append(f"# HELP {name} {help_text}")
                lines.append(f"# TYPE {name} {kind}")
                for key, v in sorted(self._counters.get(name, {}).items()):
                    lines.append(f"{name}{_labels(key)} {v:g}")
                for key, v in sorted(self._gauges.get(name, {}).items()):
                    lines.append(f"{name}{_labels(key)} {v:g}")
                for key, h in sorted(self._hists.get(name, {}).items()):
                    cum = 0
                    for bound, c in zip((*LATENCY_BUCKETS_S, float("inf")), h.counts, strict=True):
                        cum += c
                        le = "+Inf" if bound == float("inf") else f"{bound:g}"
                        lines.append(f"{name}_bucket{_labels((*key, ('le', le)))} {cum}")
                    lines.append(f"{name}_sum{_labels(key)} {h.total:.6f}")
                    lines.append(f"{name}_count{_labels(key)} {h.n}")
        return "\n".join(lines) + "\n"
