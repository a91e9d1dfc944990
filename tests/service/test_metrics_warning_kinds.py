"""``mfgnet_registration_warnings_total`` counts each warning the pipeline writes under its own kind (the text before
its colon, ``docs/DEPLOYMENT.md``, "Metrics"), so an operator sees why results were not reliable; ``other`` is only
for text the pipeline never writes."""

from __future__ import annotations

import pytest

pytest.importorskip("prometheus_client")

from service.api.metrics import WARNING_KINDS, Metrics
from service.quality import ReverseFit, target_explained
from service.stages.consensus import confirmed_note, consensus_note
from service.stages.free_space import (
    CONFIRMS_BELOW,
    RELIABLE_FREE_SPACE,
    confirmed_by_free_space,
    through_free_space,
)
from service.stages.guess_check import GuessGap, far_from_guess, guess_returned
from service.stages.search import RETRY_WARNING

# The warnings of the closing checks, as the stages write them (the others' kinds are listed in metrics.WARNING_KINDS)
CLOSING_WARNINGS = {
    "through free space": through_free_space(RELIABLE_FREE_SPACE + 0.05),
    "confirmed by free space": confirmed_by_free_space(CONFIRMS_BELOW / 2),
    "found by the second, denser rotation search only (the first fitted poorly)": RETRY_WARNING,
    "far from initial transform": far_from_guess(GuessGap(40.0, 0.01), 0.1, GuessGap(0.5, 0.001)),
    "initial transform returned": guess_returned(),
    "target explained": target_explained(0.27, ReverseFit(0.98, 0.98, 1.0)),
    "descriptor consensus": consensus_note(54, 3),
    "confirmed by descriptors": confirmed_note(41),
}


def counted_kinds(metrics: Metrics) -> dict[str, float]:
    family = next(f for f in metrics.registry.collect() if f.name == "mfgnet_registration_warnings")
    return {s.labels["kind"]: s.value for s in family.samples if s.name.endswith("_total")}


@pytest.mark.parametrize("kind", sorted(CLOSING_WARNINGS))
def test_a_closing_checks_warning_is_counted_under_its_own_kind(kind):
    metrics = Metrics()
    metrics.observe_quality("general", reliable=False, warnings=[CLOSING_WARNINGS[kind]])
    assert counted_kinds(metrics) == {kind: 1.0}
    assert kind in WARNING_KINDS


def test_text_the_pipeline_never_writes_is_other():
    metrics = Metrics()
    metrics.observe_quality("general", reliable=False, warnings=["made up: by a request", "no colon at all"])
    assert counted_kinds(metrics) == {"other": 2.0}
