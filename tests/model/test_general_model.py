"""The bundled ``general`` model (trained on independently sampled pairs) against the paper-protocol
``clean`` model on pairs whose clouds share no points."""

from __future__ import annotations

import numpy as np
import pytest

from model.data import data_dir, make_test_pairs
from service.manifest import bundled_models_dir
from service.registrar import Registrar

pytestmark = [
    pytest.mark.skipif(not (data_dir() / "modelnet40_test.npz").exists(),
                       reason=f"ModelNet40 not found at {data_dir()} (set $MFGNET_DATA)"),
    pytest.mark.skipif(not (bundled_models_dir() / "general").is_dir(), reason="no bundled 'general' model"),
]


def rotation_errors_deg(registrar: Registrar, pairs: dict) -> np.ndarray:
    errors = []
    for src, tgt, R in zip(pairs["source"], pairs["target"], pairs["rotation"], strict=True):
        res = registrar.register(src, tgt)  # the network alone: no refinement
        cos = (np.trace(res.rotation @ R.T) - 1) / 2
        errors.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return np.array(errors)


def test_general_beats_clean_on_disjoint_halves() -> None:
    pairs = make_test_pairs("resampled", count=24, seed=5)  # disjoint 384-point samples: no exact partners
    general = rotation_errors_deg(Registrar(bundled_models_dir() / "general"), pairs)
    clean = rotation_errors_deg(Registrar(bundled_models_dir() / "clean"), pairs)
    assert np.median(general) < 0.8 * np.median(clean), (np.median(general), np.median(clean))
    assert np.mean(general < 10) > np.mean(clean < 10)
