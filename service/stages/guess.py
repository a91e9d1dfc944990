"""Stage 4, guess (after the network or the search, before the features of 4a): the caller's ``initial_transform``
itself as a candidate beside the network's poses.

The network starts from the caller's guess and can move a good guess away: on the development set's real scans
started 10 deg from the truth it turned 6 of 36 cases away. With the guess as a second candidate the refinement ranks
both by their close fit and refines the better one, so a guess near the truth is kept where the network leaves it
(``docs/decisions/0037-the-callers-guess-as-a-candidate.md``). It joins the plain pass's candidates and the rotation
search's alike.

A wrong guess (one given target-to-source, say) also moves the network's start away from where the request without it
starts, and the refinement can leave both the guess and the network's pose from it in wrong basins. So where the plain
result does not keep the guess, the network's pose from the caller's own frame (:func:`unguessed_candidate`, the
request's start without the guess) is refined alone and competes with it (:func:`better_than_unguessed`); a result it
does not confirm is searched by ``auto`` as that request's would be
(``docs/decisions/0068-the-unguessed-start-competes.md``).
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from service.rotation_search import DUPLICATE_DEGREES, SearchCandidate, network_from, rotation_between_deg
from service.stages.network import Candidates
from service.stages.normalise import Working
from service.stages.ranking import candidate_fits, ranking_ambiguity
from service.stages.refine import unrefined_pick

if TYPE_CHECKING:
    from service.registrar import Registrar
    from service.result import RegistrationResult

# A result within this angle of the caller's guess keeps it: a room's other frame rotations lie a quarter or half turn
# away (docs/decisions/0037-the-callers-guess-as-a-candidate.md).
KEPT_DEG = 30.0
# A result within this angle of the network's pose from the caller's own frame, or of that pose refined (and within the
# refinement's correspondence distance where the two put the source's centroid), lies in that pose's basin: it
# confirms the result (docs/decisions/0068-the-unguessed-start-competes.md).
SAME_BASIN_DEG = 5.0


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


def doubtful_with_guess(result: RegistrationResult) -> bool:
    """Whether a ``result`` that keeps the caller's guess is not ``reliable``: a wrong guess can hold the network and
    the refinement near its turn, metres from the truth, or (``refine: "none"``) be returned as it is, so the
    request's start without the guess competes (:meth:`service.registrar.Registrar.beside_unguessed`) as it does where
    the result leaves the guess (``docs/decisions/0118-a-doubtful-guessed-result-competes.md``)."""
    return not result.reliable


def unguessed_candidate(registrar: Registrar, work: Working, iterations: int, keypoints: int,
                        timing: dict[str, float]) -> Candidates | None:
    """The network's pose from the caller's own frame: the working source turned back by the guess's rotation, the
    start the request has without the guess (normalisation centres each cloud, so the guess's translation does not
    change it), with its own network output (its correspondences, should it win); ``None`` where the guess turns the
    source less than ``DUPLICATE_DEGREES`` (the plain network's pose is then that one). Records its time in
    ``timing`` ``encoder`` and ``iterations``."""
    start = work.R_init.T  # [3, 3] the caller's source frame, seen from the guess's
    if rotation_between_deg(start, np.eye(3)) < DUPLICATE_DEGREES:
        return None
    net = network_from(registrar.start_network, work.src_n, work.tgt_n, start[None], iterations, keypoints,
                       timing).outputs()[0]
    return Candidates([SearchCandidate(net, start, net.rotation @ start, net.translation)], work.idx_s, work.idx_t)


def same_basin(work: Working, a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray],
               distance: float) -> bool:
    """Whether the poses ``a`` and ``b`` (``(R [3, 3], t [3])``, caller's frame) lie within ``SAME_BASIN_DEG`` of each
    other and place the working source's centroid within ``distance`` (caller's units) of each other."""
    centre = work.working_source.mean(axis=0)  # [3] caller's frame
    shift = np.linalg.norm(a[0] @ centre + a[1] - (b[0] @ centre + b[1]))
    return rotation_between_deg(a[0], b[0]) < SAME_BASIN_DEG and shift < distance


def better_than_unguessed(work: Working, guessed: RegistrationResult, alone: RegistrationResult, distance: float
                          ) -> tuple[RegistrationResult, bool]:
    """Whichever of the ``guessed`` plain result and ``alone`` (the network's pose from the caller's own frame, refined
    and assessed alone) fits better by the ranking's measure (:func:`service.stages.ranking.candidate_fits`;
    ``guessed`` on a tie), not ``reliable`` and with the ranking's ambiguity warning where the other fits almost as
    well and lies apart (:func:`service.stages.ranking.ranking_ambiguity`); and whether it is ``guessed`` where
    ``alone`` lies elsewhere (not in its basin, :func:`same_basin` within ``distance``): unconfirmed."""
    rotations = np.stack([guessed.rotation, alone.rotation])  # [2, 3, 3] the guessed result first: it keeps ties
    translations = np.stack([guessed.translation, alone.translation])  # [2, 3]
    fits, measure = candidate_fits(work, rotations, translations)  # [2]
    best = int(np.argmax(fits))  # the first on a tie
    kept = (guessed, alone)[best]
    warning = ranking_ambiguity(work, rotations, translations, fits, best, measure=measure)
    if warning is not None and kept.reliable:
        kept = replace(kept, reliable=False, warnings=[*kept.warnings, warning])
    pose = (guessed.rotation, guessed.translation)
    return kept, best == 0 and not same_basin(work, pose, (alone.rotation, alone.translation), distance)


def better_unrefined(work: Working, guessed: RegistrationResult, alone: RegistrationResult) -> RegistrationResult:
    """``refine: "none"``: whichever of the ``guessed`` result and ``alone`` (the network's pose from the caller's own
    frame) lies nearer the basin that fits better, ranked by short refinements as the guess and the network's pose are
    (:func:`service.stages.refine.unrefined_pick`; ``guessed`` on a tie), not ``reliable`` and with the ranking's
    ambiguity warning where it has one: unrefined poses' own fits cannot rank them (a near-symmetric surface fits a
    pose turned far away about as well)."""
    picked = unrefined_pick(work, [(guessed.rotation, guessed.translation), (alone.rotation, alone.translation)])
    kept = (guessed, alone)[picked.pick]
    if picked.ambiguity is not None and kept.reliable:
        kept = replace(kept, reliable=False, warnings=[*kept.warnings, picked.ambiguity])
    return kept
