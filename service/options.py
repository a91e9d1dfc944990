"""``RegistrationOptions``: every option of ``Registrar.register`` in one frozen, checked object.

Built directly (``RegistrationOptions(refine="icp-plane")``) or from keyword overrides
(:meth:`RegistrationOptions.of`); construction raises :class:`service.errors.InputError` naming the first bad
option. The model's own defaults (``iterations=None``, ``keypoints=None``) are resolved by
:meth:`RegistrationOptions.network`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import numpy as np

from service.checks import MIN_POINTS, check_transform
from service.errors import InputError
from service.refine_modes import REFINE_MODES, REFINE_POINTS_RANGE
from service.request_defaults import KEYPOINT_RANGE, MAX_ITERATIONS
from service.rotation_search import search_rotations_for

WORKING_SIZE_RANGE = (MIN_POINTS, 4096)
DEFAULT_WORKING_SIZE = 768
SearchMode = bool | Literal["auto"]  # rotation_search: False, True or "auto"


def search_mode(rotation_search: SearchMode | np.bool_ | None) -> Literal["off", "on", "auto"]:
    """``rotation_search`` (``False``, ``True`` or ``"auto"``; ``None``: the default, ``False``) as a mode,
    or ``InputError``."""
    if rotation_search is None:
        return "off"
    if rotation_search is False or rotation_search is True or isinstance(rotation_search, np.bool_):
        return "on" if rotation_search else "off"
    if isinstance(rotation_search, str) and rotation_search == "auto":
        return "auto"
    raise InputError(f"rotation_search must be true, false or 'auto', got {rotation_search!r}")


def check_iterations(iterations: int) -> None:
    if not 1 <= iterations <= MAX_ITERATIONS:
        raise InputError(f"iterations must be in 1..{MAX_ITERATIONS}, got {iterations}")


def check_working_size(working_size: int) -> None:
    low, high = WORKING_SIZE_RANGE
    if not low <= working_size <= high:
        raise InputError(f"working_size must be in {low}..{high}, got {working_size}")


def check_keypoints(keypoints: int, working_size: int) -> None:
    if not KEYPOINT_RANGE[0] <= keypoints <= KEYPOINT_RANGE[1]:
        raise InputError(f"keypoints must be in {KEYPOINT_RANGE[0]}..{KEYPOINT_RANGE[1]}, got {keypoints}")
    if keypoints > working_size:
        raise InputError(f"keypoints ({keypoints}) cannot exceed the working size ({working_size})")


def check_network(iterations: int, keypoints: int, working_size: int) -> None:
    """Range checks of the network's settings (resolved: no ``None``), in the order callers see them."""
    check_iterations(iterations)
    check_working_size(working_size)
    check_keypoints(keypoints, working_size)


def whole_number(value: object, name: str) -> int:
    """``value`` as an ``int`` where it is a whole number (``64``, ``64.0``, ``"64"``, a numpy integer), else
    ``InputError`` naming ``name``: ``64.7`` is refused, not cut to 64, as the server refuses it."""
    if isinstance(value, (bool, np.bool_)):
        raise InputError(f"{name} must be a whole number, got {value!r}")
    try:
        number = float(value)
        whole = int(number)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{name} must be a whole number, got {value!r}") from None
    if number != whole:
        raise InputError(f"{name} must be a whole number, got {value!r}")
    return whole


def check_flag(value: object, name: str) -> None:
    """``InputError`` unless ``value`` is ``True`` or ``False`` (a numpy bool too): ``"false"`` is not ``False``."""
    if not isinstance(value, (bool, np.bool_)):
        raise InputError(f"{name} must be true or false, got {value!r}")


def check_refinement(refine: str | None, refine_points: int | None) -> None:
    if refine is not None and refine not in REFINE_MODES:
        raise InputError(f"refine must be one of {REFINE_MODES}, got {refine!r}")
    low, high = REFINE_POINTS_RANGE
    if refine_points is not None and not low <= whole_number(refine_points, "refine_points") <= high:
        raise InputError(f"refine_points must be in {low}..{high}, got {refine_points}")


def check_refine_points_refined(refine: str, refine_points: int | None, defaulted: bool = False) -> None:
    """``InputError`` where ``refine_points`` comes with ``refine`` ``"none"`` (``defaulted``: the server's default,
    not the request's), which runs no refinement for it to shape; the command line's usage error says the same."""
    if refine == "none" and refine_points is not None:
        whose = " (the server's default, MFGNET_DEFAULT_REFINE)" if defaulted else ""
        raise InputError(f"refine_points sets the refinement's clouds; refine none{whose} runs no refinement")


@dataclass(frozen=True, eq=False)
class RegistrationOptions:
    """How ``Registrar.register`` registers a pair.

    ``iterations`` / ``keypoints``: ``None`` = the model's. ``refine``: one of
    :data:`service.refine_modes.REFINE_MODES` (``None`` = ``"none"``, the network's pose alone).
    ``initial_transform``: a rigid 4x4 ``src_to_tgt`` guess; the source is moved by it before sampling, and the
    guess itself is a candidate beside the network's poses (:mod:`service.stages.guess`; ranked by short refinements,
    also with ``refine`` ``"none"``, which returns the winner unrefined).
    ``working_size``: points per working cloud; ``return_iterations``: the pose after every network iteration.

    ``rotation_search=True`` starts the network from ``search_rotations`` initial rotations of the
    source about its centroid (:mod:`service.rotation_search`: 24 or 60), ``SEARCH_BATCH`` starts per encoder and
    matcher call against a target embedded once; without a refinement it keeps the hypothesis whose pose has the
    highest inlier ratio on the working clouds (ties: lower residual). With
    ``refine="icp"`` every hypothesis first gets a short wide-basin ICP (``SEARCH_ICP_*``) and
    the ranking uses those poses (with an early-training network the raw poses rarely land
    close enough to rank the right basin first; ``docs/ROTATION_SEARCH.md``); the winner then
    gets the usual ICP (mutual nearest neighbours, ``icp_max_distance``) to convergence.
    ``refine="icp-plane"`` refines with point-to-plane ICP instead (:func:`service.icp.refine_plane`: a
    wide-basin robust symmetric stage at 3x the distance, then reciprocal point-to-plane at
    ``icp_max_distance``; each stage at most ``icp_max_iterations``): much closer than point-to-point
    between independently sampled scans (``docs/DESIGN.md``, "Refinement"). With the
    rotation search the per-hypothesis short ICPs stay point-to-point. With any refinement the search
    returns its ``SEARCH_KEEP`` best hypotheses; each distinct one gets a short refinement (``refine``'s stages
    with at most ``CANDIDATE_ITERATIONS`` updates each), they are ranked again on the working clouds, and the
    winner gets the full refinement. With any refinement, where both working clouds are built of orthogonal
    planes (room fragments; :mod:`service.plane_frames`), the candidates are instead the ``SEARCH_KEEP`` rotations
    between the clouds' plane frames that overlay them best, whatever ``search_rotations`` is (one of the 24 lies
    within a few degrees of a right rotation). With any refinement, a model whose manifest has a ``search`` section
    (those trained on independently sampled pairs) searches on that many points spread evenly through each
    working cloud's rows with at most that many keypoints, and the winner is refined on the full clouds;
    its correspondences are then those of the subsample (that many).
    ``refine="icp-plane-multistart"`` then turns the refined pose by
    +-15 and +-30 degrees about each axis, moves each turn with a short ICP and keeps the best fit by
    a two-way point-to-plane score, refined again (:mod:`service.multistart`). When a refinement
    stops on a degenerate system (too few pairs, a planar or linear target) it keeps the pose it had
    and adds a warning; ``reliable`` still comes from :func:`service.quality.assess` alone.
    ``drop_isolated`` (default): isolated points -- flying pixels, sparse clutter; a mean distance to their
    8 nearest others above 3x the cloud's median (:func:`service.sampling.isolated_points`) -- are left
    out of the working and refinement clouds, so the network and the refinement see the surfaces
    (``docs/ACCURACY.md``, "Outliers"); returned indices never point at them.
    ``refine_points``: the refinement moves up to this many points of the caller's source onto up to this
    many target points (every point up to that many, else one per voxel: :func:`service.sampling.spread_indices`)
    instead of the working clouds; more points give a more precise pose on dense scans at a
    higher cost (``docs/ACCURACY.md``, "Refinement on more points"). ``quality`` stays measured on the
    working clouds. With ``refine`` ``None`` / ``"none"``, an ``InputError`` (no refinement to shape), as is
    ``icp_max_distance``.
    ``timing_ms["search"]`` is the whole search (network, short ICPs, ranking) and
    ``timing_ms["search_per_hypothesis"]`` that divided by the number of hypotheses.

    ``rotation_search="auto"`` runs the plain registration (with ``refine``) first and returns it
    unchanged unless it looks wrong (:func:`service.stages.search.needs_search`: an inlier ratio below
    ``AUTO_SEARCH_RELATIVE_RATIO`` of what the target's density allows, and not the look of a partial view's right
    pose: :func:`service.stages.partial.looks_partial`) and neither working cloud is
    degenerate (identical or collinear points, or fewer than 32 distinct ones: no start rotation can fix what they
    leave open); then it
    runs the rotation search as above on the same working clouds and returns whichever of the two final poses
    :func:`service.rotation_search.rank_hypotheses`
    ranks first (inlier ratio, then residual; the plain one on a tie). The stage keys of ``timing_ms``
    are the plain pass's; ``"search"`` (the whole second pass: hypotheses, short ICPs, ranking, the
    winner's refinement and quality, the final comparison) and ``"search_per_hypothesis"`` are present
    exactly when the search ran; ``"total"`` covers both.
    """

    iterations: int | None = None
    keypoints: int | None = None
    refine: str | None = None
    initial_transform: object | None = None  # [4, 4] src_to_tgt
    working_size: int = DEFAULT_WORKING_SIZE
    return_iterations: bool = False
    icp_max_distance: float | None = None  # caller's units; None: ICP_DISTANCE x the clouds' scale
    icp_max_iterations: int = 30
    rotation_search: SearchMode = False
    search_rotations: int = 24
    refine_points: int | None = None
    drop_isolated: bool = True

    def __post_init__(self) -> None:
        """Every check that needs no model; the first bad option raises ``InputError``."""
        if self.iterations is not None:
            check_iterations(whole_number(self.iterations, "iterations"))
        check_working_size(whole_number(self.working_size, "working_size"))
        if self.keypoints is not None:
            check_keypoints(whole_number(self.keypoints, "keypoints"), self.working_size)
        check_refinement(self.refine, self.refine_points)
        check_refine_points_refined(self.refine or "none", self.refine_points)
        check_flag(self.return_iterations, "return_iterations")
        check_flag(self.drop_isolated, "drop_isolated")
        if self.icp_max_distance is not None and not (
                isinstance(self.icp_max_distance, (int, float, np.number)) and 0 < self.icp_max_distance < np.inf):
            raise InputError(f"icp_max_distance must be a positive number, got {self.icp_max_distance!r}")
        if self.icp_max_distance is not None and self.refine_mode == "none":  # as refine_points: it would be ignored
            raise InputError("icp_max_distance sets the refinement's pairing distance; refine none runs no refinement")
        # 0: the refinement stage keeps its start; the slide check and the fine refinement after it still move the
        # pose (their own caps), so an unrefined pose, judged as one, is refine="none"
        if whole_number(self.icp_max_iterations, "icp_max_iterations") < 0:
            raise InputError(f"icp_max_iterations must be at least 0, got {self.icp_max_iterations}")
        search_mode(self.rotation_search)  # true, false or "auto"
        search_rotations_for(whole_number(self.search_rotations, "search_rotations"))  # whether or not a search runs
        if self.initial_transform is not None:
            check_transform(self.initial_transform)

    @property
    def extra_refine_points(self) -> int | None:
        """``refine_points`` where it asks for more points than the working clouds hold, else ``None``: the
        refinement never runs on fewer points than the network's working clouds (a thinner refinement moves a right
        pose off by degrees while ``quality``, measured on the working clouds, can stay ``reliable``)."""
        if self.refine_points is None or int(self.refine_points) <= int(self.working_size):
            return None
        return int(self.refine_points)

    @classmethod
    def of(cls, options: RegistrationOptions | None = None, **overrides) -> RegistrationOptions:
        """``options`` (default: all defaults) with ``overrides`` (field names; ``TypeError`` for others)."""
        if options is None:
            return cls(**overrides)
        return dataclasses.replace(options, **overrides) if overrides else options

    @classmethod
    def names(cls) -> frozenset[str]:
        """The option names ``Registrar.register`` takes as keyword overrides."""
        return frozenset(f.name for f in dataclasses.fields(cls))

    @property
    def refine_mode(self) -> str:
        """``refine`` with ``None`` spelled ``"none"``."""
        return self.refine or "none"

    @property
    def search(self) -> Literal["off", "on", "auto"]:
        return search_mode(self.rotation_search)

    def network(self, default_iterations: int, default_keypoints: int) -> tuple[int, int]:
        """``(iterations, keypoints)`` with the model's defaults filled in, range-checked."""
        n_iter = default_iterations if self.iterations is None else int(self.iterations)
        k = default_keypoints if self.keypoints is None else int(self.keypoints)
        check_network(n_iter, k, self.working_size)
        return n_iter, k
