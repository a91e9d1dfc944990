"""Every discovered model folder, loaded into a :class:`Registrar` by a background thread.

Liveness answers at once; readiness waits until each model has been verified (sha256), loaded and
warmed up. A model that fails (missing or tampered files, bad manifest) is not served and keeps the
reason. Names are only ever looked up in the registry's dict, so a request naming
``../../etc/passwd`` is a 404 and never a file access.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from service.api.errors import APIError, shortened
from service.core.logging import APP_LOGGER
from service.manifest import ModelIntegrityError, bundled_models_dir, discover_model_dirs
from service.registrar import Registrar

log = logging.getLogger(APP_LOGGER)

RETRY_AFTER_LOADING_S = 2


def unknown_model(name: str) -> APIError:
    """The 404 for a model name no entry has (the name cut short: a path may be 100 KB)."""
    return APIError(404, f"unknown model {shortened(name)!r}; see GET /v1/models")


@dataclass
class ModelEntry:
    name: str
    directory: Path  # never shown to clients
    status: str = "loading"  # loading | ready | failed
    error: str | None = None
    registrar: Registrar | None = None
    load_seconds: float | None = None


class UnknownModelsError(ValueError):
    """``MFGNET_MODELS`` names a model that no model folder holds, or ``MFGNET_DEFAULT_MODEL`` one not served."""


class ModelRegistry:
    """Model name -> :class:`ModelEntry`; ``start()`` loads them all in a daemon thread."""

    def __init__(
        self,
        directories: list[Path],
        threads: int | None = None,
        strict: bool = True,
        loader: Callable[..., Registrar] = Registrar,
        on_loaded: Callable[[ModelEntry], None] | None = None,
    ):
        self.threads = threads
        self.strict = strict
        self.loader = loader
        self.on_loaded = on_loaded
        self.entries: dict[str, ModelEntry] = {}
        self.duplicates: list[str] = []
        for directory in directories:
            if directory.name in self.entries:
                self.duplicates.append(directory.name)
                log.warning("two model folders of one name; serving the first", extra={
                    "model": directory.name, "served": str(self.entries[directory.name].directory),
                    "not_served": str(directory)})
                continue
            self.entries[directory.name] = ModelEntry(directory.name, directory)
        self.finished = threading.Event()
        self._thread: threading.Thread | None = None

    @classmethod
    def discover(
        cls, extra_dirs: list[str], bundled: bool = True, only: list[str] | None = None, **kwargs
    ) -> ModelRegistry:
        """Model folders under ``extra_dirs``, then the bundled ones (a folder of ``extra_dirs`` takes the place of a
        bundled model of its name, as ``mfgnet register --model-dir`` does); ``only``: keep these names.

        Raises:
            UnknownModelsError: when ``only`` names a model that was not found.
        """
        root = bundled_models_dir().resolve()
        try:
            found = discover_model_dirs(extra_dirs)
        except OSError as exc:  # a folder this user may not read (a volume of another owner): one line, exit code 2
            raise UnknownModelsError(f"model folder {exc.filename}: {exc.strerror} (MFGNET_MODEL_DIRS or "
                                     "--model-dir)") from None
        in_bundle = [d for d in found if d.resolve().parent == root]
        found = [d for d in found if d not in in_bundle] + (in_bundle if bundled else [])
        if only:
            missing = sorted(set(only) - {d.name for d in found})
            if missing:
                names = ", ".join(sorted(d.name for d in found)) or "none"
                raise UnknownModelsError(f"MFGNET_MODELS names models that were not found: {', '.join(missing)} "
                                         f"(found: {names})")
            found = [d for d in found if d.name in only]
        return cls(found, **kwargs)

    # -- loading ---------------------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self.load_all, name="mfgnet-model-loader", daemon=True)
        self._thread.start()

    def load_all(self) -> None:
        try:
            for entry in self.entries.values():
                self._load(entry)
        finally:
            self.finished.set()

    def _load(self, entry: ModelEntry) -> None:
        started = time.perf_counter()
        try:
            registrar = self.loader(entry.directory, threads=self.threads, warmup=True)
        except ModelIntegrityError as exc:
            entry.status, entry.error = "failed", str(exc)
        except Exception as exc:  # ORT refusing a graph, a crash in warm-up, ...: the reason stays server-side
            entry.status, entry.error = "failed", f"could not load the model ({type(exc).__name__}); see the log"
            log.exception("model failed to load", extra={"model": entry.name})
        else:
            entry.registrar, entry.load_seconds, entry.status = registrar, time.perf_counter() - started, "ready"
            log.info("model ready", extra={"model": entry.name, "load_seconds": round(entry.load_seconds, 3)})
            if self.on_loaded is not None:
                self.on_loaded(entry)
            return
        log.error("model not served", extra={"model": entry.name, "reason": entry.error})

    # -- queries ---------------------------------------------------------------------------------
    def statuses(self) -> dict[str, str]:
        return {name: entry.status for name, entry in self.entries.items()}

    def readiness(self) -> tuple[bool, str]:
        """``(ready, reason)``: ready once loading finished, a model is served and (strict) none failed."""
        statuses = self.statuses()
        served = sum(s == "ready" for s in statuses.values())
        failed = sorted(n for n, s in statuses.items() if s == "failed")
        if not self.entries:
            return False, "no model found (bundled service/models or MFGNET_MODEL_DIRS)"
        if any(s == "loading" for s in statuses.values()):
            return False, f"loading models: {served} of {len(statuses)} ready"
        reasons = "; ".join(f"{name}: {self.entries[name].error}" for name in failed)
        if not served:
            return False, f"no model could be loaded (failed: {reasons})"
        if self.strict and failed:
            return False, f"models failed to load: {reasons} (MFGNET_STRICT_READINESS)"
        return True, "ready"

    def errors(self) -> dict[str, str]:
        """Model name -> why it is not served, for every failed model."""
        return {name: e.error or "failed" for name, e in self.entries.items() if e.status == "failed"}

    def get(self, name: str) -> ModelEntry:
        """The served model ``name``: 404 if unknown, 503 if still loading or failed."""
        entry = self.entries.get(name)  # a dict lookup only: never a path
        if entry is None:
            raise unknown_model(name)
        if entry.status == "loading":
            raise APIError(
                503, f"model {name!r} is still loading", headers={"Retry-After": str(RETRY_AFTER_LOADING_S)}
            )
        if entry.status == "failed":
            raise APIError(503, f"model {name!r} is not served: {entry.error}")
        return entry
