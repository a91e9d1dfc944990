"""Model directories: ``manifest.json`` + ONNX graphs, verified by sha256 before anything is loaded."""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

MANIFEST = "manifest.json"
FORMAT = 1  # the manifest format this runtime reads (``mfgnet export`` writes it as "format")
MODEL_NAME = re.compile(r"^[a-z0-9][a-z0-9_.-]{0,63}$")


class ModelIntegrityError(RuntimeError):
    """A model directory is incomplete or a file does not match its manifest hash."""


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass(frozen=True)
class Manifest:
    """A verified model directory."""

    directory: Path
    name: str
    version: str
    sha256: str  # of manifest.json itself
    config: dict
    graphs: dict[str, Path]  # role ("encoder", "matcher_0", ...) -> verified file
    normalization: dict
    accuracy: dict = field(default_factory=dict)
    raw: dict = field(default_factory=dict)
    # The rotation search's subsample when a refinement follows: (points per working cloud, keypoints), or None
    # for the full working clouds. Written by the export for models trained on independently sampled pairs;
    # models trained on the paper's shared points match exact points and search the full clouds.
    search_subsample: tuple[int, int] | None = None

    def graph_bytes(self, role: str) -> bytes:
        """The graph's bytes, read ONCE and checked against the manifest hash: the runtime builds its
        session from these bytes, so a file swapped after ``load_manifest`` can never be served."""
        data = self.graphs[role].read_bytes()
        if hashlib.sha256(data).hexdigest() != self.raw["graphs"][role]["sha256"]:
            raise ModelIntegrityError(
                f"model {self.name!r}: sha256 of {self.graphs[role].name} does not match the manifest"
            )
        return data

    @property
    def matcher_roles(self) -> list[str]:
        count = sum(1 for role in self.graphs if role.startswith("matcher_"))
        return [f"matcher_{i}" for i in range(count)]


def load_manifest(directory: str | Path) -> Manifest:
    """Read ``directory/manifest.json`` and verify every graph's sha256.

    Raises:
        ModelIntegrityError: missing or malformed manifest, missing graph, hash mismatch, or a
            folder name that differs from the manifest's ``name``.
    """
    directory = Path(directory)
    path = directory / MANIFEST
    if not path.is_file():
        raise ModelIntegrityError(f"model {directory.name!r}: {MANIFEST} is missing")
    try:
        raw = json.loads(path.read_text())
        name, version, graphs = raw["name"], str(raw["version"]), raw["graphs"]
        config, normalization = raw["config"], raw["normalization"]
    except KeyError as exc:
        raise ModelIntegrityError(f"model {directory.name!r}: malformed {MANIFEST} (no {exc.args[0]!r} field)"
                                  ) from None
    except (ValueError, TypeError) as exc:
        raise ModelIntegrityError(f"model {directory.name!r}: malformed {MANIFEST} ({exc})") from None
    if name != directory.name or not MODEL_NAME.match(name):
        raise ModelIntegrityError(f"model folder {directory.name!r} does not match manifest name {name!r}")
    if raw.get("format", FORMAT) != FORMAT:  # written by an export newer (or other) than this runtime
        raise ModelIntegrityError(f"model {name!r}: manifest format {raw['format']!r}; this runtime reads {FORMAT}")
    problems = config_problems(config)
    if problems:
        raise ModelIntegrityError(f"model {name!r}: malformed config in {MANIFEST}: {'; '.join(problems)}")
    radius = normalization.get("reference_radius") if isinstance(normalization, dict) else None
    if type(radius) not in (int, float) or not math.isfinite(radius) or radius <= 0:
        raise ModelIntegrityError(f"model {name!r}: normalization.reference_radius is {radius!r}, not a number "
                                  "above 0 (the radius the runtime scales clouds to)")
    verified: dict[str, Path] = {}
    for role, entry in graphs.items():
        file = directory / Path(entry["file"]).name  # never leave the model directory
        if not file.is_file():
            raise ModelIntegrityError(f"model {name!r}: graph file {file.name} is missing")
        if sha256_file(file) != entry["sha256"]:
            raise ModelIntegrityError(f"model {name!r}: sha256 of {file.name} does not match the manifest")
        verified[role] = file
    if "encoder" not in verified or "matcher_0" not in verified:
        raise ModelIntegrityError(f"model {name!r}: manifest needs an encoder and at least one matcher")
    return Manifest(
        directory, name, version, sha256_file(path), config, verified, normalization, raw.get("accuracy", {}), raw,
        _search_subsample(name, raw.get("search")),
    )


def config_problems(config: object) -> list[str]:
    """What in a manifest's ``config`` the runtime cannot run (a hand-edited or damaged manifest), each named; the
    graphs' own shapes are checked against it when they load (``Registrar``)."""
    from service.request_defaults import KEYPOINT_RANGE, MAX_ITERATIONS

    if not isinstance(config, dict):
        return [f"config is {type(config).__name__}, not an object"]
    wanted = {
        "iterations": lambda v: type(v) is int and 1 <= v <= MAX_ITERATIONS,
        "keypoints": lambda v: type(v) is int and KEYPOINT_RANGE[0] <= v <= KEYPOINT_RANGE[1],
        "knn": lambda v: type(v) is int and v >= 1,
        "centroid": lambda v: v in ("weighted", "unweighted"),
    }
    return [f"{key} {config[key]!r}" for key, ok in wanted.items() if key in config and not ok(config[key])]


def _search_subsample(name: str, section: dict | None) -> tuple[int, int] | None:
    """The manifest's optional ``search`` section ``{"points": P, "keypoints": K}`` -> ``(P, K)``."""
    if section is None:
        return None
    try:
        points, keypoints = section["points"], section["keypoints"]
        valid = all(type(v) is int for v in (points, keypoints)) and 16 <= keypoints <= points
    except (KeyError, TypeError):
        valid = False
    if not valid:
        raise ModelIntegrityError(
            f"model {name!r}: malformed search section {section!r} (integers points >= keypoints >= 16)"
        )
    return points, keypoints


def bundled_models_dir() -> Path:
    """``service/models`` inside the installed package (works for wheels and editable installs)."""
    return Path(str(resources.files("service") / "models"))


def model_folder(model: str | Path) -> Path:
    """A model's folder: the bundled model of that name where ``model`` is a bare name (a folder of that name in the
    working directory, e.g. an export's ``--out general``, does not hide it: write ``./general`` for that one), else
    ``model`` itself when it is a directory, else the bundled model of that name."""
    bundled = bundled_models_dir() / model
    if is_bare_name(model) and bundled.is_dir():
        return bundled
    return Path(model) if Path(model).is_dir() else bundled


def is_bare_name(model: str | Path) -> bool:
    """Whether ``model`` is a name, not a path: a ``str`` with no folder separator that does not begin with ``.``."""
    return isinstance(model, str) and not any(sep in model for sep in ("/", os.sep)) and not model.startswith(".")


def discover_model_dirs(extra_dirs: list[str | Path] | None = None) -> list[Path]:
    """Bundled model folders, then every model folder inside (or equal to) each extra directory."""
    roots = [bundled_models_dir(), *[Path(d) for d in extra_dirs or []]]
    return [folder for root in roots for folder in models_in(root)]


def models_in(root: Path) -> list[Path]:
    """``[root]`` where it is a model folder, else the model folders inside it (none where it is no folder)."""
    if looks_like_model(root):
        return [root]
    return sorted(p for p in root.iterdir() if p.is_dir() and looks_like_model(p)) if root.is_dir() else []


def looks_like_model(path: Path) -> bool:
    """A folder with a manifest or ONNX graphs (one without a manifest is reported, not skipped)."""
    return path.is_dir() and ((path / MANIFEST).is_file() or any(path.glob("*.onnx")))
