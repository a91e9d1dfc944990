"""Prometheus metrics, in a registry of their own per app (several apps can live in one process)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, disable_created_metrics

from service.quality import SCATTERED_POINTS, TARGET_EXPLAINED
from service.stages.consensus import CONFIRMED_BY_DESCRIPTORS, DESCRIPTOR_CONSENSUS
from service.stages.float32_check import FLOAT32_ROUNDING
from service.stages.free_space import CONFIRMED_BY_FREE_SPACE, THROUGH_FREE_SPACE
from service.stages.guess_check import FAR_FROM_GUESS, GUESS_RETURNED
from service.stages.scale_check import SIZE_MISMATCH
from service.stages.search import RETRY_WARNING

# No ``<counter>_created`` / ``<histogram>_created`` series: in the text format Prometheus stores each as one more gauge
# series per label set (the counters' series doubled), undocumented and unused; rate() needs none of them. The switch
# is process-wide: the service's registries are the only ones in its process.
disable_created_metrics()

LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)
# Warning kinds are the text before a warning's colon ("weakly constrained", "target coplanar", ...): a fixed set
# in this code base; anything else is counted as "other" so that no request can grow the label set.
WARNING_KINDS = frozenset({
    "low overlap", "poor fit", "loose fit", "weakly constrained", "ambiguous", "refinement",
    *(f"{cloud} {kind}" for cloud in ("source", "target")
      for kind in ("empty", "identical", "collinear", "few distinct points", "coplanar")),
    THROUGH_FREE_SPACE, CONFIRMED_BY_FREE_SPACE, RETRY_WARNING.split(":", 1)[0],  # the closing checks'
    FAR_FROM_GUESS,  # a result far from the caller's initial_transform (service.stages.guess_check)
    GUESS_RETURNED,  # an unrefined result that is the caller's initial_transform as given, not reliable (same stage)
    SIZE_MISMATCH,  # clouds whose sizes differ as units do (service.stages.scale_check)
    FLOAT32_ROUNDING,  # float32 coordinates far from the origin (service.stages.float32_check)
    TARGET_EXPLAINED,  # a result whose source explains a cut target (service.quality)
    SCATTERED_POINTS,  # clouds whose points lie farther apart than the inlier distance (service.quality)
    DESCRIPTOR_CONSENSUS,  # a result the descriptors' consensus gave (service.stages.consensus)
    CONFIRMED_BY_DESCRIPTORS,  # a result the descriptors made `reliable` (service.stages.consensus)
})


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "mfgnet_http_requests",
            "HTTP requests answered (or given up by their client: status 499) by route template, method and status.",
            ["route", "method", "status"], registry=self.registry,
        )
        self.header_timeouts = Counter(
            "mfgnet_http_header_timeouts",
            "Connections answered 408 and closed because a request's line and headers did not arrive within "
            "MFGNET_HEADER_TIMEOUT_S of its first byte (slow or stalled clients, slowloris).",
            registry=self.registry,
        )
        self.connections_refused = Counter(
            "mfgnet_http_connections_refused",
            "Connections answered 503 and closed on arrival because MFGNET_MAX_CONNECTIONS were open and none was "
            "idle.",
            registry=self.registry,
        )
        self.latency = Histogram(
            "mfgnet_http_request_duration_seconds",
            "Seconds from a request's arrival to its last response byte, by route template.",
            ["route"], buckets=LATENCY_BUCKETS, registry=self.registry,
        )
        self.in_flight = Gauge(
            "mfgnet_http_requests_in_flight", "HTTP requests being handled (a scrape counts itself).",
            registry=self.registry,
        )
        self.stage = Histogram(
            "mfgnet_pipeline_stage_seconds",
            "Seconds of each registration pipeline stage (each returned result's timing_ms, in seconds).",
            ["model", "stage"], buckets=LATENCY_BUCKETS, registry=self.registry,
        )
        self.slots = Gauge(
            "mfgnet_inference_slots_taken",
            "Registrations being read, waiting or running, and aligned answers (/v1/register/aligned) until their file "
            "is sent.",
            registry=self.registry,
        )
        self.body_bytes = Gauge(
            "mfgnet_body_bytes_held", "Bytes of JSON and OIP bodies being read or waiting to be decoded "
            "(at most MFGNET_MAX_BUFFERED_BYTES).", registry=self.registry,
        )
        self.running = Gauge("mfgnet_inference_running", "Registrations running in a worker.", registry=self.registry)
        self.model_load = Gauge(
            "mfgnet_model_load_seconds", "Seconds taken to verify, load and warm up each model.", ["model"],
            registry=self.registry,
        )
        self.results = Counter(
            "mfgnet_registration_results",
            "Registrations by model and whether the result is reliable (quality.reliable): a rising unreliable share "
            "means the clouds changed (sensor, scene, overlap) or the model does not fit them.",
            ["model", "reliable"], registry=self.registry,
        )
        self.warnings = Counter(
            "mfgnet_registration_warnings", "Warnings of the returned registrations by model and kind (the text before "
            "the colon: 'weakly constrained', 'low overlap', 'ambiguous', ...; 'other' for any other).",
            ["model", "kind"], registry=self.registry,
        )
        self.model_ready = Gauge(
            "mfgnet_model_ready", "1 when the model is served, 0 while loading or failed.", ["model"],
            registry=self.registry,
        )

    def observe_timing(self, model: str, timing_ms: dict[str, float]) -> None:
        for stage, ms in timing_ms.items():
            self.stage.labels(model=model, stage=stage).observe(ms / 1000)

    def observe_quality(self, model: str, reliable: bool, warnings: list[str]) -> None:
        """Count one returned registration and each of its warnings by kind."""
        self.results.labels(model=model, reliable=str(bool(reliable)).lower()).inc()
        for warning in warnings:
            kind = warning.split(":", 1)[0]
            self.warnings.labels(model=model, kind=kind if kind in WARNING_KINDS else "other").inc()
