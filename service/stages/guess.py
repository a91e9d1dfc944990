"""Stage 4, guess (after the network or the search, before the features of 4a): the caller's ``initial_transform``
itself as a candidate beside the network's poses.

The network starts from the caller's guess and can move a good guess away: on the development set's real scans
started 10 deg from the truth it turned 6 of 36 cases away. With the guess as a second candidate the refinement ranks
both by their close fit and refines the better one, so a guess near the truth is kept where the network leaves it
(``docs/decisions/0037-the-callers-guess-as-a-candidate.md``). It joins the plain pass's candidates and the rotation
search's alike.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from service.rotation_search import SearchCandidate, rotation_between_deg
from service.stages.network import Candidates
from service.stages.normalise import Working

if TYPE_CHECKING:
    from service.result import RegistrationResult

# A result within this angle of the caller's guess keeps it: a room's other frame rotations lie a quarter or half turn
# away (docs/decisions/0037-the-callers-guess-as-a-candidate.md).
KEPT_DEG = 30.0


def guess_candidate(work: Working, found: Candidates) -> Candidates:
    """``found`` and, after it, the initial guess: the identity in the guess's frame, normalised. It carries the first
    candidate's network output and start (its correspondences and iteration poses, should it win): in the plain pass
    the network's from that very start; after a search, the best search candidate's. It runs before the feature stage,
    which appends its candidate last (:func:`service.stages.features.feature_confirmed`)."""
    rotation, translation = work.norm.normalize_pose(np.eye(3), np.zeros(3))  # [3, 3], [3]
    first = found.poses[0]
    guess = SearchCandidate(first.network, first.start, rotation, translation)  # a deferred output stays so
    return Candidates([*found.poses, guess], found.net_s, found.net_t)


def keeps_guess(work: Working, result: RegistrationResult) -> bool:
    """Whether ``result`` (caller's frame) lies within ``KEPT_DEG`` of the initial guess: the caller's prior then tells
    which of a room's frame rotations is right, and ``auto`` does not search a room for being one
    (:func:`service.stages.search.looks_wrong`). The registrar asks only where the caller gave a guess."""
    return rotation_between_deg(work.R_init, result.rotation) < KEPT_DEG
