"""A real range image cut to 60% of its points against its whole partner: the cut source is smaller than the
target, so the inlier distance (set by the source's size) fell below the working target's point spacing, the
density's attainable inlier ratio was 0, and a pose 134 deg off came back ``reliable``."""

from __future__ import annotations

import dataclasses
from dataclasses import replace

import numpy as np
from real_scan_cases import GENERAL, real_case, register_with_defaults, skip_without

from bench.altered_scans import ALTERATIONS, altered, cases
from bench.real_scans import Case, data_dir, pose_errors, thresholds
from service.quality import TARGET_EXPLAINED
from service.registrar import Registrar
from service.stages.assess import RELIABLE_STABILITY_ON_SURFACE
from service.stages.pipeline import Stages


def test_a_cropped_range_image_is_not_called_reliable_when_wrong() -> None:
    case = real_case("dragon_72_24", 0, "scanned")
    rng = np.random.default_rng([ALTERATIONS.index("crop"), sum(map(ord, "dragon_72_24"))])
    source, target = altered("crop", case.source, case.target, rng)  # the source's 60% on one side of a plane
    result, degrees, error = register_with_defaults(replace(case, source=source, target=target))
    max_degrees, max_error = thresholds(case.sensor)
    right = degrees < max_degrees and error < max_error
    assert right or not result.reliable, (degrees, error, result.warnings)


def test_a_cut_room_fragment_half_a_turn_off_is_weakly_constrained_on_its_dense_target() -> None:
    """``3dlo_kitchen_34_21`` with its source cut (``bench.altered_scans``'s ``crop``) and turned comes back about half
    a turn off, on a patch of the target that fits it better than the right pose does: no fit tells them apart, but the
    patch pins the pose down less than a dense target pins a right one (decisions/0050). Judged before the consensus
    stage, which gives this not-reliable result another pose (16 matched patches against 5, also wrong)."""
    skip_without("3dlo_kitchen_34_21")
    _, sensor, source, target, truth, _ = next(
        c for c in cases(data_dir(), "crop", names=["3dlo_kitchen_34_21"]) if c[0].endswith("/turned"))
    no_consensus = Registrar(GENERAL, stages=dataclasses.replace(Stages(), consensus=lambda *a: a[2]))
    result = no_consensus.register(source, target, refine="icp-plane", rotation_search="auto")
    degrees, error = pose_errors(result.rotation, result.translation, truth)
    max_degrees, max_error = thresholds(sensor)
    if degrees < max_degrees and error < max_error:
        return  # a right pose may be reliable; the pipeline found it
    assert result.stability < RELIABLE_STABILITY_ON_SURFACE and not result.reliable, (degrees, result.stability)
    assert any(w.startswith("weakly constrained") and f"< {RELIABLE_STABILITY_ON_SURFACE:g}" in w
               for w in result.warnings), result.warnings


def test_a_range_image_registered_to_a_cut_partner_is_reliable_where_the_source_explains_it():
    """``dragon_144_96`` with its target cut to 60% (``bench.altered_scans``' ``croptarget``) registers right, but
    only 0.27 of the source lies on the smaller target: the source-side ratio alone called it ``low overlap``. Measured
    the other way, 0.98 of the target lies on the moved source (decisions/0084)."""
    skip_without("dragon_144_96")
    label, sensor, source, target, truth, _ = next(cases(data_dir(), "croptarget", names=["dragon_144_96"]))
    result, degrees, error = register_with_defaults(Case(label, sensor, "scanned", 1.0, source, target, truth))
    max_degrees, max_error = thresholds(sensor)
    assert degrees < max_degrees and error < max_error, (degrees, error)
    assert result.inlier_ratio < 0.3 and result.reliable, result.warnings
    assert [w.split(":")[0] for w in result.warnings] == [TARGET_EXPLAINED]
