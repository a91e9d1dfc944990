"""The torch twin ``model.pose.weighted_procrustes`` agrees with the numpy one in ``service``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from model.pose import compose as compose_torch
from model.pose import transform_points
from model.pose import weighted_procrustes as procrustes_torch
from service.procrustes import compose as compose_numpy
from service.procrustes import weighted_procrustes as procrustes_numpy


def random_batch(seed: int, batch: int = 8, k: int = 32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noisy correspondences ``src, tgt (batch, k, 3)`` and weights ``(batch, k)`` (some rows all zero)."""
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(batch, k, 3))
    q, _ = np.linalg.qr(rng.normal(size=(batch, 3, 3)))
    R = q * np.sign(np.linalg.det(q))[:, None, None]  # proper rotations
    tgt = (
        np.einsum("bij,bkj->bki", R, src)
        + rng.normal(size=(batch, 1, 3))
        + rng.normal(scale=0.1, size=src.shape)
    )
    weights = rng.uniform(size=(batch, k)) * (rng.uniform(size=(batch, k)) > 0.3)
    weights[0] = 0.0  # all-zero row: uniform fallback in both twins
    return src, tgt, weights


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("centroid", ["weighted", "unweighted"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_torch_twin_matches_numpy(seed: int, centroid: str, dtype: type) -> None:
    src, tgt, weights = (a.astype(dtype) for a in random_batch(seed))
    R_np, t_np = procrustes_numpy(src, tgt, weights, centroid)
    R_pt, t_pt = procrustes_torch(
        torch.from_numpy(src), torch.from_numpy(tgt), torch.from_numpy(weights), centroid
    )
    assert R_pt.dtype == torch.from_numpy(src).dtype
    np.testing.assert_allclose(R_pt.numpy(), R_np, atol=1e-5)
    np.testing.assert_allclose(t_pt.numpy(), t_np, atol=1e-5)


def test_torch_twin_matches_numpy_without_weights() -> None:
    src, tgt, _ = random_batch(3)
    R_np, t_np = procrustes_numpy(src, tgt)
    R_pt, t_pt = procrustes_torch(torch.from_numpy(src), torch.from_numpy(tgt))
    np.testing.assert_allclose(R_pt.numpy(), R_np, atol=1e-10)
    np.testing.assert_allclose(t_pt.numpy(), t_np, atol=1e-10)


def test_torch_twin_matches_numpy_with_tiny_weights() -> None:
    src = torch.randn(2, 64, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    tgt = src + torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    weights = torch.full((2, 64), 1e-10, dtype=torch.float64)
    R, t = procrustes_torch(src, tgt, weights)
    R_np, t_np = procrustes_numpy(src.numpy(), tgt.numpy(), weights.numpy())
    np.testing.assert_allclose(t.numpy(), t_np, atol=1e-9)
    np.testing.assert_allclose(t.numpy(), [[1.0, 2.0, 3.0]] * 2, atol=1e-9)
    np.testing.assert_allclose(R.numpy(), R_np, atol=1e-9)


def test_torch_rotations_are_proper() -> None:
    src, tgt, weights = random_batch(4)
    R, _ = procrustes_torch(torch.from_numpy(src), torch.from_numpy(-tgt), torch.from_numpy(weights))
    np.testing.assert_allclose(torch.linalg.det(R).numpy(), 1.0, atol=1e-10)


def test_compose_and_transform_match_numpy() -> None:
    src, tgt, weights = random_batch(5, batch=2)
    R_a, t_a = procrustes_numpy(src, tgt, weights)
    R_b, t_b = procrustes_numpy(tgt, src, weights)
    R_np, t_np = compose_numpy(R_b, t_b, R_a, t_a)
    R_pt, t_pt = compose_torch(*(torch.from_numpy(a) for a in (R_b, t_b, R_a, t_a)))
    np.testing.assert_allclose(R_pt.numpy(), R_np, atol=1e-12)
    np.testing.assert_allclose(t_pt.numpy(), t_np, atol=1e-12)
    moved = transform_points(torch.from_numpy(src), torch.from_numpy(R_a), torch.from_numpy(t_a))
    np.testing.assert_allclose(moved.numpy(), np.einsum("bij,bkj->bki", R_a, src) + t_a[:, None], atol=1e-12)
