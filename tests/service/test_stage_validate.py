"""Stages validate, sample and normalise on their own: checked request -> working clouds -> normalised clouds."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import bumpy_ellipsoid

from service.errors import InputError
from service.options import RegistrationOptions
from service.stages.normalise import INLIER_DISTANCE, normalise, to_caller
from service.stages.sample import sample
from service.stages.validate import validate


def request(src=None, tgt=None, options=None, **overrides):
    src = bumpy_ellipsoid(900) if src is None else src
    tgt = bumpy_ellipsoid(700, seed=1) if tgt is None else tgt
    return validate(src, tgt, options, overrides, 3, 128)


def test_validate_checks_the_clouds_before_the_options() -> None:
    with pytest.raises(InputError, match="source: needs at least 32 points"):
        request(src=np.zeros((5, 3)), refine="plane")
    with pytest.raises(InputError, match="target: expected shape"):
        request(tgt=np.zeros((50, 2)), refine="plane")
    with pytest.raises(InputError, match="refine must be one of"):
        request(refine="plane")


def test_validate_fills_in_the_model_defaults_the_guess_and_the_search_starts() -> None:
    guess = np.eye(4)
    guess[:3, :3] = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    guess[:3, 3] = [1.0, 2.0, 3.0]
    r = request(options=RegistrationOptions(iterations=2), initial_transform=guess, rotation_search="auto")
    assert (r.iterations, r.keypoints, r.options.iterations) == (2, 128, 2)
    np.testing.assert_array_equal(r.R_init, guess[:3, :3])
    np.testing.assert_array_equal(r.t_init, guess[:3, 3])
    assert r.hypotheses is not None and r.hypotheses.shape == (24, 3, 3)
    plain = request()
    assert plain.hypotheses is None and np.array_equal(plain.R_init, np.eye(3)) and r.src.dtype == np.float64


def test_validate_takes_a_printed_pose_as_its_nearest_rotation() -> None:
    truth = Rotation.from_euler("zyx", [100, -35, 60], degrees=True).as_matrix()
    printed = np.eye(4)
    printed[:3, :3], printed[:3, 3] = np.round(truth, 3), [0.25, -1.5, 2.0]  # a pose written with three decimals
    assert np.abs(printed[:3, :3] @ printed[:3, :3].T - np.eye(3)).max() > 1e-4  # not orthonormal as written
    r = request(initial_transform=printed)
    np.testing.assert_allclose(r.R_init @ r.R_init.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r.R_init) == pytest.approx(1.0) and np.abs(r.R_init - truth).max() < 1e-3
    np.testing.assert_array_equal(r.t_init, printed[:3, 3])


@pytest.mark.parametrize(("matrix", "message"), [
    (np.diag([1.01, 1.01, 1.01, 1.0]), r"off by 0\.0201"),  # a scale of 1%
    (np.diag([1.0, 1.0, -1.0, 1.0]), "det \\+1"),  # a reflection
    (np.r_[np.c_[np.eye(3) + np.triu(np.full((3, 3), 0.01), 1), np.zeros(3)], [[0, 0, 0, 1]]], "off by 0.01"),  # shear
])
def test_validate_refuses_a_transform_that_is_not_rigid(matrix, message) -> None:
    with pytest.raises(InputError, match="initial_transform must be rigid") as raised:
        request(initial_transform=matrix)
    assert raised.match(message)


def test_sample_takes_working_rows_and_refinement_clouds() -> None:
    s = sample(request(working_size=256, refine="icp-plane"))
    assert (len(s.idx_s), len(s.idx_t)) == (256, 256) and s.tgt_r is s.tgt_w  # the refinement's: the working ones
    np.testing.assert_array_equal(s.src_r, s.working_source)
    more = sample(request(working_size=256, refine="icp-plane", refine_points=600))
    assert 256 < len(more.src_r) <= 600 and 256 < len(more.tgt_r) <= 600  # one per voxel: about 600
    with pytest.raises(InputError, match="refine none runs no refinement"):  # nothing to use them for
        request(working_size=256, refine_points=600)


def test_sample_never_refines_on_fewer_points_than_the_working_clouds() -> None:
    """One point per voxel of a grid sized for 800, less the sparse voxels, is 735 points of this ellipsoid: fewer
    than the 768 working points. A thinned LiDAR frame's 687 refined a 42 deg start into a 37 deg basin."""
    s = sample(request(bumpy_ellipsoid(20_000), bumpy_ellipsoid(20_000, seed=1), refine="icp-plane",
                       refine_points=800))
    assert len(s.src_r) >= len(s.src_w) and len(s.tgt_r) >= len(s.tgt_w), (len(s.src_r), len(s.tgt_r))
    assert s.refines_on_working_clouds  # either sample thinner: both working clouds, as without the option
    assert s.src_r is s.working_source and s.tgt_r is s.tgt_w


def test_sample_moves_the_source_by_the_initial_guess() -> None:
    guess = np.eye(4)
    guess[:3, 3] = [5.0, 0.0, 0.0]
    s = sample(request(initial_transform=guess))
    np.testing.assert_allclose(s.src_w, s.working_source + np.array([5.0, 0.0, 0.0]))


def test_normalise_gives_float32_clouds_and_poses_back_in_the_callers_frame() -> None:
    guess = np.eye(4)
    guess[:3, 3] = [0.5, -0.2, 0.1]
    work = normalise(sample(request(initial_transform=guess, working_size=256)), 1.0)
    assert work.src_n.dtype == work.tgt_n.dtype == np.float32 and work.src_n.shape == (256, 3)
    assert work.inlier_distance == INLIER_DISTANCE * work.norm.scale
    R, t = to_caller(work, np.eye(3), np.zeros(3))  # the identity between normalised clouds
    moved = work.working_source @ R.T + t  # [Ns, 3]
    np.testing.assert_allclose(work.norm.apply_tgt(moved), work.norm.apply_src(work.src_w), atol=1e-9)
