"""A ``reliable`` result that a later check withdraws: the notes that confirmed it go with it.

The descriptor consensus (:mod:`service.stages.consensus`) and the free-space check (:mod:`service.stages.free_space`)
make a doubtful result ``reliable`` with a note saying what confirmed it; a check after them (free space, the symmetry
check) can still find it wrong. Its warning then replaces the note, which would otherwise stand beside a refusal.
"""

from __future__ import annotations

import dataclasses

from service.result import RegistrationResult

CONFIRMED_BY_DESCRIPTORS = "confirmed by descriptors"  # first words of the consensus' note on a result it made reliable
CONFIRMED_BY_FREE_SPACE = "confirmed by free space"  # ... and of the free-space check's
CONFIRMATIONS = (CONFIRMED_BY_DESCRIPTORS, CONFIRMED_BY_FREE_SPACE)


def withdrawn(result: RegistrationResult, warning: str) -> RegistrationResult:
    """``result`` not ``reliable``, with ``warning`` added and its :data:`CONFIRMATIONS` notes left out."""
    kept = [w for w in result.warnings if not w.startswith(CONFIRMATIONS)]
    return dataclasses.replace(result, reliable=False, warnings=[*kept, warning])
