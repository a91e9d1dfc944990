"""Checkpoint files: a dict of tensors and plain values, always read with ``weights_only=True``."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import torch

from model.config import MFGNetConfig
from model.network import MFGNet

BUNDLED_DIR = Path(__file__).resolve().parent / "checkpoints"


def resolve_checkpoint(name_or_path: str | os.PathLike) -> Path:
    """A path, or the name of a bundled checkpoint (``clean`` -> ``model/checkpoints/clean.pt``); a bare name is the
    bundled checkpoint's even beside a folder of that name (an export's ``--out general``; ``./general`` is that)."""
    from service.manifest import is_bare_name

    path = Path(name_or_path)
    bundled = BUNDLED_DIR / f"{name_or_path}.pt"
    if is_bare_name(name_or_path) and bundled.exists():
        return bundled
    if path.exists():
        return path
    if bundled.exists():
        return bundled
    raise FileNotFoundError(f"no checkpoint file or bundled checkpoint named {name_or_path!r}")


def save_checkpoint(path: str | os.PathLike, model: MFGNet, **extra) -> None:
    """Atomically write ``{"model": state_dict, "config": {...}, **extra}``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save({"model": model.state_dict(), "config": model.cfg.to_dict(), **extra}, tmp)
    os.replace(tmp, path)


def read_checkpoint(path: str | os.PathLike) -> dict:
    return torch.load(resolve_checkpoint(path), map_location="cpu", weights_only=True)


def load_model(path: str | os.PathLike) -> MFGNet:
    """The network of a checkpoint, in eval mode."""
    data = read_checkpoint(path)
    model = MFGNet(MFGNetConfig.from_dict(data["config"]))
    model.load_state_dict(data["model"])
    return model.eval()


def weights_mismatch(model: torch.nn.Module, weights: dict) -> str | None:
    """Why ``weights`` would not load into ``model`` (missing or unexpected keys, other shapes), or ``None``."""
    expected = model.state_dict()
    missing = [key for key in expected if key not in weights]
    unexpected = [key for key in weights if key not in expected]
    reshaped = [key for key in expected if key in weights
                and (not isinstance(weights[key], torch.Tensor) or weights[key].shape != expected[key].shape)]
    problems = []
    if missing:
        problems.append(f"{len(missing)} weights missing ({missing[0]}, ...)")
    if unexpected:
        problems.append(f"{len(unexpected)} unexpected ({unexpected[0]!r}, ...)")
    if reshaped:
        key, value = reshaped[0], weights[reshaped[0]]
        got = list(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
        problems.append(f"{len(reshaped)} of another shape ({key}: {got}, the network's {list(expected[key].shape)})")
    return "; ".join(problems) or None


def file_sha256(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def bundle_checkpoint(run_dir: str | os.PathLike, name: str, which: str = "best.pt") -> Path:
    """Copy a run's weights (no optimizer state), config, provenance and log into ``model/checkpoints/<name>.*``."""
    import json
    import math
    import shutil

    run_dir = Path(run_dir)
    data = torch.load(run_dir / which, map_location="cpu", weights_only=True)
    keep = {k: data[k] for k in ("model", "config", "state", "protocol", "setting", "val", "provenance") if k in data}
    BUNDLED_DIR.mkdir(parents=True, exist_ok=True)
    target = BUNDLED_DIR / f"{name}.pt"
    torch.save(keep, target)
    state = {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
             for k, v in (data.get("state") or {}).items()}  # strict JSON: no Infinity
    (BUNDLED_DIR / f"{name}.json").write_text(
        json.dumps({"config": data["config"], "from": f"{run_dir.name}/{which}", "state": state,
                    "val": data.get("val"), "provenance": data.get("provenance")}, indent=2) + "\n")
    if (run_dir / "log.jsonl").exists():
        shutil.copyfile(run_dir / "log.jsonl", BUNDLED_DIR / f"{name}.log.jsonl")
    return target
