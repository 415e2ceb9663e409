"""Prometheus metrics of one server (prometheus-client, its own registry so that servers in one process,
as in the tests, do not share counters). Served at ``/metrics`` in the text exposition format."""

from __future__ import annotations

from prometheus_client import (
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    disable_created_metrics,
    generate_latest,
)
from prometheus_client.exposition import CONTENT_TYPE_LATEST

disable_created_metrics()  # the *_created series double the output and no dashboard reads them

# Stage latencies span 10 µs (decode) to tens of ms (an overloaded session): log-spaced buckets, seconds.
STAGE_BUCKETS_S = (
    1e-5, 2.5e-5, 5e-5, 1e-4, 2.5e-4, 5e-4, 1e-3, 2e-3, 3e-3, 5e-3, 8e-3, 11.1e-3, 15e-3, 25e-3, 50e-3, 0.1, 0.25,
)  # fmt: skip
CONTENT_TYPE = CONTENT_TYPE_LATEST


class Metrics:
    """Every metric the server exports; names start with ``egoposevr_``."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.sessions = Gauge("egoposevr_sessions", "Sessions open now", registry=r)
        self.clients = Gauge("egoposevr_clients", "Connected clients by role", ["role"], registry=r)
        self.connections = Counter("egoposevr_connections", "WebSocket connections accepted", registry=r)
        self.messages = Counter("egoposevr_messages", "Messages received by type", ["type"], registry=r)
        self.errors = Counter("egoposevr_errors", "Error replies sent, by code", ["code"], registry=r)
        self.poses = Counter("egoposevr_poses", "Poses produced, by model", ["model"], registry=r)
        self.skipped_samples = Counter(
            "egoposevr_skipped_samples", "Headset samples answered by no pose (newest won)", registry=r
        )
        self.replaced_frames = Counter(
            "egoposevr_replaced_frames", "RGB-D frames replaced by a newer one before use", registry=r
        )
        self.stale_frames = Counter(
            "egoposevr_stale_frames", "RGB-D frames refused as not newer than the cached ones", registry=r
        )
        self.dropped_poses = Counter(
            "egoposevr_dropped_poses", "Poses dropped from a slow client's queue", ["role"], registry=r
        )
        self.rate_limited = Counter(
            "egoposevr_rate_limited_messages", "Messages dropped by the per-session rate cap", registry=r
        )
        self.recordings_failed = Counter(
            "egoposevr_recordings_failed",
            "Recordings (--record) that stopped on an error, e.g. a full disk",
            registry=r,
        )
        self.models_loaded = Gauge("egoposevr_models_loaded", "Models servable now", registry=r)
        self.execution_provider = Gauge(
            "egoposevr_execution_provider", "1 for each onnxruntime execution provider models run on",
            ["provider"], registry=r,
        )  # fmt: skip
        self.model_failures = Gauge("egoposevr_model_failures", "Model files that failed to load", registry=r)
        self.stage_seconds = Histogram(
            "egoposevr_stage_seconds", "Server time per pose by stage", ["stage"], buckets=STAGE_BUCKETS_S,
            registry=r,
        )  # fmt: skip

        self.batch_size = Histogram(
            "egoposevr_batch_size", "Sessions whose headset jobs ran as one batch (one fusion-net call)",
            buckets=(1, 2, 3, 4, 6, 8, 12, 16, 32, 64), registry=r,
        )  # fmt: skip

    def observe_timing(self, timing_us: dict[str, int]) -> None:
        for stage, us in timing_us.items():
            self.stage_seconds.labels(stage).observe(us * 1e-6)

    def exposition(self) -> bytes:
        return generate_latest(self.registry)
