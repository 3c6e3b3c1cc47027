"""Prometheus metrics of one service process, on ``prometheus-client``.

Each ``Metrics`` owns its own ``CollectorRegistry`` (several apps can live in one test process) with the
standard process, platform and garbage-collector collectors, build and model info, and the service's own:

- ``reradar_http_requests_total{method,route,status}`` counter
- ``reradar_http_request_duration_seconds{method,route}`` histogram
- ``reradar_stage_duration_seconds{stage}`` histogram (decode, extract, retrieve, screen, pose, ...)
- ``reradar_localizations_total{status}`` counter
- ``reradar_maps_loaded``, ``reradar_scan_cache_entries`` gauges
- ``reradar_build_info{version,python,torch,faiss,onnxruntime}``, ``reradar_model_info{model_id,weights_sha256,network_runtime}``

In a fleet every replica is scraped on its own ``/metrics``; Prometheus sums them.
"""

from __future__ import annotations

import platform
from importlib import metadata

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    Info,
    disable_created_metrics,
    generate_latest,
)
from prometheus_client.gc_collector import GCCollector
from prometheus_client.platform_collector import PlatformCollector
from prometheus_client.process_collector import ProcessCollector

__all__ = ["Metrics", "LATENCY_BUCKETS_S", "CONTENT_TYPE_LATEST"]

# the *_created series double the output and no dashboard of ours reads them
disable_created_metrics()

#: Histogram bucket upper bounds, seconds.
LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0, 2.5, 5.0, 10.0)


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "unknown"


class Metrics:
    """The service's metrics registry; thread-safe (prometheus-client metrics are)."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        ProcessCollector(registry=self.registry)
        PlatformCollector(registry=self.registry)
        GCCollector(registry=self.registry)
        r = self.registry
        self._counters: dict[str, Counter] = {
            "reradar_http_requests_total": Counter(
                "reradar_http_requests", "HTTP requests by method, route template and status.",
                ["method", "route", "status"], registry=r),
            "reradar_localizations_total": Counter(
                "reradar_localizations", "Localization outcomes by status.", ["status"], registry=r),
        }
        self._hists: dict[str, Histogram] = {
            "reradar_http_request_duration_seconds": Histogram(
                "reradar_http_request_duration_seconds", "HTTP request latency, seconds.", ["method", "route"],
                buckets=LATENCY_BUCKETS_S, registry=r),
            "reradar_stage_duration_seconds": Histogram(
                "reradar_stage_duration_seconds", "Pipeline stage latency, seconds.", ["stage"],
                buckets=LATENCY_BUCKETS_S, registry=r),
        }
        self._gauges: dict[str, Gauge] = {
            "reradar_maps_loaded": Gauge("reradar_maps_loaded", "Maps ready for queries.", registry=r),
            "reradar_scan_cache_entries": Gauge(
                "reradar_scan_cache_entries", "Uploaded scans held in this process's feature cache.", registry=r),
        }
        self.build_info = Info("reradar_build", "Versions of ReRadar and its runtime.", registry=r)
        self.build_info.info({"version": _version("reradar"), "python": platform.python_version(),
                              "torch": _version("torch"), "faiss": _version("faiss-cpu"),
                              "onnxruntime": _version("onnxruntime")})
        self.model_info = Info("reradar_model", "Descriptor model served.", registry=r)

    def set_model(self, model_id: str, weights_sha256: str, network_runtime: str = "torch") -> None:
        """Record the loaded descriptor model (``reradar_model_info``) and where its network runs ("onnx": ONNX
        Runtime, "torch": torch; ``reradar_core.model.runtime``)."""
        self.model_info.info({"model_id": model_id, "weights_sha256": weights_sha256,
                              "network_runtime": network_runtime})

    def inc(self, name: str, value: float = 1.0, **labels: str) -> None:
        counter = self._counters[name]
        (counter.labels(**labels) if labels else counter).inc(value)

    def observe(self, name: str, seconds: float, **labels: str) -> None:
        hist = self._hists[name]
        (hist.labels(**labels) if labels else hist).observe(seconds)

    def set_gauge(self, name: str, value: float, **labels: str) -> None:
        gauge = self._gauges[name]
        (gauge.labels(**labels) if labels else gauge).set(value)

    def observe_stages(self, timings_ms: dict[str, float]) -> None:
        """Observe every ``<stage>_ms`` entry except ``total_ms`` in the stage histogram."""
        for stage, ms in timings_ms.items():
            if stage.endswith("_ms") and stage != "total_ms":
                self._hists["reradar_stage_duration_seconds"].labels(stage=stage[:-3]).observe(ms / 1e3)

    def render(self) -> str:
        """Prometheus text exposition format 0.0.4."""
        return generate_latest(self.registry).decode()
