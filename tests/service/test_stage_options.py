"""``RegistrationOptions``: one frozen, checked options object with the messages ``Registrar.register`` gives."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from service.errors import InputError
from service.options import DEFAULT_WORKING_SIZE, RegistrationOptions


def test_defaults_are_the_former_keyword_defaults() -> None:
    o = RegistrationOptions()
    assert (o.iterations, o.keypoints, o.refine, o.initial_transform) == (None, None, None, None)
    assert (o.working_size, o.icp_max_iterations, o.search_rotations) == (DEFAULT_WORKING_SIZE, 30, 24)
    assert (o.rotation_search, o.drop_isolated, o.return_iterations, o.refine_points) == (False, True, False, None)
    assert o.refine_mode == "none" and o.search == "off"


def test_is_frozen_and_overrides_make_a_new_checked_object() -> None:
    base = RegistrationOptions(refine="icp")
    with pytest.raises(dataclasses.FrozenInstanceError):
        base.refine = "icp-plane"  # type: ignore[misc]
    plane = RegistrationOptions.of(base, refine="icp-plane", rotation_search="auto")
    assert (base.refine, plane.refine, plane.search) == ("icp", "icp-plane", "auto")
    assert RegistrationOptions.of(base) is base and RegistrationOptions.of(None, keypoints=64).keypoints == 64
    with pytest.raises(InputError, match="refine must be one of"):
        RegistrationOptions.of(base, refine="plane")
    with pytest.raises(TypeError):
        RegistrationOptions.of(None, keypoint=64)  # a misspelt option is not silently ignored
    assert "rotation_search" in RegistrationOptions.names() and len(RegistrationOptions.names()) == 12


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"iterations": 0}, "iterations must be in 1..8, got 0"),
        ({"working_size": 16}, "working_size must be in 32..4096, got 16"),
        ({"keypoints": 4}, "keypoints must be in 16..512, got 4"),
        ({"keypoints": 300, "working_size": 256}, r"keypoints \(300\) cannot exceed the working size \(256\)"),
        ({"refine": "plane"}, "refine must be one of"),
        ({"refine_points": 10}, "refine_points must be in 32..8192, got 10"),
        ({"rotation_search": "sometimes"}, "rotation_search must be true, false or 'auto'"),
        ({"rotation_search": True, "search_rotations": 7}, "search_rotations must be one of"),
        ({"initial_transform": np.eye(3)}, "initial_transform must be 4x4"),
        ({"initial_transform": np.diag([2.0, 1, 1, 1])}, "initial_transform must be rigid"),
        ({"iterations": 0, "refine": "plane"}, "iterations"),  # the first bad option in the former order
    ],
)
def test_bad_options_raise_the_former_messages(options, message) -> None:
    with pytest.raises(InputError, match=message):
        RegistrationOptions(**options)


def test_search_rotations_is_checked_whether_or_not_a_search_runs() -> None:
    """A value no search takes is refused with the search off too: it was ignored then, and refused once on."""
    with pytest.raises(InputError, match="search_rotations must be one of"):
        RegistrationOptions(search_rotations=7)
    assert RegistrationOptions(search_rotations=60).search == "off"
    assert RegistrationOptions(rotation_search=np.bool_(True)).search == "on"
    assert RegistrationOptions(rotation_search=None).search == "off"


def test_network_fills_in_the_models_defaults_and_checks_them() -> None:
    assert RegistrationOptions().network(3, 128) == (3, 128)
    assert RegistrationOptions(iterations=2.0, keypoints=np.int64(64)).network(3, 128) == (2, 64)
    with pytest.raises(InputError, match=r"keypoints \(128\) cannot exceed the working size \(64\)"):
        RegistrationOptions(working_size=64).network(3, 128)


def test_refine_points_with_the_servers_default_of_no_refinement_names_that_default():
    from service.errors import InputError
    from service.options import check_refine_points_refined

    check_refine_points_refined("icp-plane", 1000)
    check_refine_points_refined("none", None, defaulted=True)
    with pytest.raises(InputError, match=r"refine none \(the server's default, MFGNET_DEFAULT_REFINE\) runs no "):
        check_refine_points_refined("none", 1000, defaulted=True)
