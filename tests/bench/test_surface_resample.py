"""bench.surface_resample: clouds made denser on their own surface, and the fused fragments of bench.real_scans."""

import numpy as np
import pytest

from bench import real_scans
from bench.surface_resample import DISC_SHARE, NOISE_SHARE, densified, point_spacing
from service.kdtree import KDTree


def plane_grid(step: float = 0.01, side: int = 40) -> np.ndarray:
    """``[side**2, 3]`` float32: a square grid on the plane z = 0."""
    x, y = np.meshgrid(np.arange(side) * step, np.arange(side) * step)
    return np.stack([x.ravel(), y.ravel(), np.zeros(side * side)], axis=1).astype(np.float32)


def test_point_spacing_is_the_grid_step():
    assert point_spacing(plane_grid(0.01)) == pytest.approx(0.01, rel=1e-4)


def test_densified_points_cover_the_surface_and_stay_on_it():
    grid = plane_grid(0.01)
    dense = densified(grid, 16 * len(grid), np.random.default_rng(0))
    assert dense.shape == (16 * len(grid), 3) and dense.dtype == np.float32
    assert dense[:, 2].std() == pytest.approx(NOISE_SHARE * 0.01, rel=0.1)  # noise along the normal only
    assert np.abs(dense[:, 2]).max() < 6 * NOISE_SHARE * 0.01
    nearest = KDTree(grid).query(dense, k=1)[0]
    assert nearest.max() < DISC_SHARE * 0.01 + 6 * NOISE_SHARE * 0.01  # within each parent's disc
    assert point_spacing(dense) < 0.5 * 0.01  # denser than the grid: the discs fill the gaps


def test_densified_is_seeded_and_refuses_fewer_points():
    grid = plane_grid(0.01, side=12)
    np.testing.assert_array_equal(densified(grid, 500, np.random.default_rng(3)),
                                  densified(grid, 500, np.random.default_rng(3)))
    assert np.abs(densified(grid, 500, np.random.default_rng(3)) - densified(grid, 500, np.random.default_rng(4))
                  ).max() > 0
    with pytest.raises(ValueError, match="at least the 144 points"):
        densified(grid, 100, np.random.default_rng(0))


def test_only_fused_fragments_are_densified_and_their_turns_share_the_clouds(tmp_path):
    grid = plane_grid(0.025, side=30)
    bent = np.concatenate([grid, grid[:, [2, 0, 1]]])  # [1800, 3] two walls: a PCA plane everywhere
    shift = np.eye(4)
    shift[:3, 3] = 0.1
    for name, sensor in (("room_1_0", "kinect-fused-2.5cm"), ("dragon_1_0", "cyberware-range")):
        np.savez(tmp_path / f"{name}.npz", source=bent, target=bent + 0.1, transform=shift, sensor=sensor)
    cases = real_scans.load_cases(tmp_path, seed=1, scales=(1.0,), turns=2, densify=5000)
    sizes = {(c.name, c.variant): (len(c.source), len(c.target)) for c in cases}
    assert sizes[("room_1_0", "scanned")] == sizes[("room_1_0", "turned-2")] == (5000, 5000)
    assert sizes[("dragon_1_0", "scanned")] == (1800, 1800)
    room = [c for c in cases if c.name == "room_1_0"]
    for case in room:  # the ground truth still takes each (turned) source onto the same densified target
        moved = case.source @ case.src_to_tgt[:3, :3].T + case.src_to_tgt[:3, 3]
        np.testing.assert_allclose(moved.mean(0), room[0].source.mean(0) + 0.1, atol=1e-4)
    again = real_scans.load_cases(tmp_path, seed=1, scales=(1.0,), names=["room_1_0"], densify=5000)
    np.testing.assert_array_equal(again[0].source, room[0].source)  # the same clouds whichever pairs are loaded


def test_densify_above_the_services_file_limit_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        real_scans.main([str(tmp_path), "--densify", str(real_scans.MAX_FILE_POINTS + 1), "--no-fpfh"])
    assert "--densify must be 1 to 2,000,000 points" in capsys.readouterr().err
