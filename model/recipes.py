"""Training recipes: per-batch random pair protocols for models meant for real scans.

The paper's settings draw every pair with one fixed protocol in which source and target are the
same points. ``general`` instead draws, for every batch, a protocol in which the two clouds are
sampled independently (disjoint halves, or two random subsets with noise so that no point has an
exact partner), with a random overlap, noise level and density mismatch, so that the network
learns to match surfaces rather than identical points. With ``views_share`` some batches are cut as
two camera views (:mod:`model.views`: only the surface facing each camera), as range scans are. With
``sensor_share`` some batches are simulated sensor pairs instead (:mod:`model.sensor_pairs`: range-image density,
range noise, flying pixels, room-like scenes of several objects on planes, any orientation).

``real`` is ``general`` at any orientation (``max_angle_deg`` 180) with ``sensor_share`` 0.6: the recipe for models
meant for real scans (issue 28), fine-tuned from ``general``. ``search`` is ``real`` as the rotation search sees it:
every cloud at the search's 128 points, rotations within 65 deg (each rotation lies within 62.8 deg of one of the
search's 24 starts): the recipe for a network that only runs the search.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from model.data import NOISE_CLIP_SIGMAS, PairProtocol
from model.sensor_pairs import KINDS, SensorProtocol
from model.sensor_sim import SensorEffects
from service.rotation_search import SEARCH_POINTS

RECIPES = ("general", "real", "search")
MIN_CLOUD_POINTS = 128  # training samples 64 keypoints with a partner + 64 without per cloud (model.config)


@dataclass(frozen=True)
class GeneralRecipe:
    """Ranges of the ``general`` recipe (each batch draws one protocol from them)."""

    max_angle_deg: float = 60.0
    overlap: tuple[float, float] = (0.6, 1.0)  # fraction of each cloud kept by the crop
    disjoint_share: float = 0.5  # batches from disjoint 512-point halves; the rest two random 768-point subsets
    disjoint_noise: tuple[float, float] = (0.0, 0.01)  # sigma range for disjoint halves
    subset_noise: tuple[float, float] = (0.004, 0.012)  # sigma range for subsets (always > 0: no exact partners)
    mismatch_share: float = 0.3  # batches where one cloud keeps only part of its crop
    mismatch_keep: tuple[float, float] = (0.5, 0.9)  # fraction kept by the sparser cloud
    outliers: float = 0.0  # most share of scattered points per cloud; each batch draws its share in [0, this]
    views_share: float = 0.0  # batches cut as camera views (model.views: range scans) instead of the far-point crop
    view_keep: tuple[float, float] = (0.2, 0.3)  # views: fraction of a cloud's points kept (a view shows ~1/3)
    view_angle_deg: float = 60.0  # views: the target's camera turned from the source's by up to this angle
    sensor_share: float = 0.0  # batches of simulated sensor pairs (model.sensor_pairs) instead of the above
    sensor_points: tuple[int, int] = (384, 768)  # sensor pairs: points per cloud, drawn per batch and cloud
    sensor_scene_share: float = 0.5  # sensor pairs: share of room-like scenes (the rest: single objects)
    sensor_spread_share: float = 0.5  # sensor pairs: share sampled as the runtime does (else a random subset)
    sensor_view_angle_deg: float = 75.0  # sensor object pairs: largest angle between the two cameras
    sensor_noise: tuple[float, float] = (0.0005, 0.004)  # range noise sigma / distance
    sensor_distance_power: tuple[float, float] = (0.0, 2.0)  # density ~ distance^-power (0: fused, 2: one image)
    sensor_mixed: tuple[float, float] = (0.0, 0.03)  # flying points at depth discontinuities / kept points
    sensor_half_angle_deg: tuple[float, float] = (25.0, 35.0)  # scenes: the cameras' cone of view
    cloud_points: int | None = None  # every cloud of the other batches sampled to this many points (None: as drawn)

    def draw(self, rng: np.random.Generator) -> PairProtocol | SensorProtocol:
        """One batch's protocol."""
        disjoint = rng.random() < self.disjoint_share
        points = 512 if disjoint else 768
        keep = round(rng.uniform(*self.overlap) * points)
        sigma = rng.uniform(*(self.disjoint_noise if disjoint else self.subset_noise))
        counts: dict[str, int | float] = {}
        if rng.random() < self.mismatch_share:
            sparse = "source_points" if rng.random() < 0.5 else "target_points"
            counts[sparse] = max(MIN_CLOUD_POINTS, round(rng.uniform(*self.mismatch_keep) * keep))
        if self.cloud_points is not None:
            counts = {"source_points": self.cloud_points, "target_points": self.cloud_points}
        if self.outliers > 0:  # drawn last: without outliers the draws are the ones the bundled model saw
            counts["outliers"] = float(rng.uniform(0.0, self.outliers))
        views: dict = {}
        if self.views_share > 0 and rng.random() < self.views_share:  # drawn after everything else, as outliers
            view_keep = max(MIN_CLOUD_POINTS, round(rng.uniform(*self.view_keep) * points))
            for name in ("source_points", "target_points"):  # a sparser cloud keeps its share of the view
                if name in counts:
                    counts[name] = min(view_keep, max(MIN_CLOUD_POINTS, round(counts[name] * view_keep / keep)))
            keep, views = view_keep, {"crop": "views", "view_angle_deg": self.view_angle_deg}
        protocol = PairProtocol(
            points=points, keep=keep, max_angle_deg=self.max_angle_deg, noise_sigma=float(sigma),
            noise_clip=NOISE_CLIP_SIGMAS * float(sigma), sampling="disjoint" if disjoint else "independent",
            **counts, **views,
        )
        protocol.check()
        if self.sensor_share > 0 and rng.random() < self.sensor_share:  # drawn last: general's draws unchanged
            return self.draw_sensor(rng)
        return protocol

    def draw_sensor(self, rng: np.random.Generator) -> SensorProtocol:
        """One batch's sensor-pair protocol."""
        scene = rng.random() < self.sensor_scene_share
        effects = SensorEffects(
            half_angle_deg=float(rng.uniform(*self.sensor_half_angle_deg)) if scene else 180.0,
            distance_power=float(rng.uniform(*self.sensor_distance_power)),
            relative_noise=float(rng.uniform(*self.sensor_noise)),
            mixed_share=float(rng.uniform(*self.sensor_mixed)),
        )
        low, high = self.sensor_points
        protocol = SensorProtocol(
            kind=KINDS[int(scene)], source_points=int(rng.integers(low, high + 1)),
            target_points=int(rng.integers(low, high + 1)), max_angle_deg=self.max_angle_deg,
            view_angle_deg=self.sensor_view_angle_deg,
            sampling="spread" if rng.random() < self.sensor_spread_share else "random", effects=effects,
        )
        protocol.check()
        return protocol


REAL = GeneralRecipe(max_angle_deg=180.0, sensor_share=0.6)
SEARCH = dataclasses.replace(REAL, max_angle_deg=65.0, cloud_points=SEARCH_POINTS,  # the search's rows per cloud
                             sensor_points=(SEARCH_POINTS, SEARCH_POINTS))


def recipe_draw(name: str, max_angle_deg: float | None = None, outliers: float | None = None,
                views_share: float | None = None,
                sensor_share: float | None = None) -> Callable[[np.random.Generator], PairProtocol | SensorProtocol]:
    """The per-batch protocol draw of a named recipe (``max_angle_deg`` overrides its rotation range,
    ``outliers`` its largest share of scattered points, ``views_share`` its share of camera-view batches,
    ``sensor_share`` its share of simulated sensor batches)."""
    if name not in RECIPES:
        raise ValueError(f"unknown recipe {name!r}; expected one of {RECIPES}")
    for label, share in (("views_share", views_share), ("sensor_share", sensor_share)):
        if share is not None and not 0.0 <= share <= 1.0:
            raise ValueError(f"{label} must be in 0..1, got {share}")
    recipe = {"real": REAL, "search": SEARCH}.get(name, GeneralRecipe())
    if max_angle_deg is not None:
        recipe = dataclasses.replace(recipe, max_angle_deg=float(max_angle_deg))
    if outliers is not None:
        recipe = dataclasses.replace(recipe, outliers=float(outliers))
    if views_share is not None:
        recipe = dataclasses.replace(recipe, views_share=float(views_share))
    if sensor_share is not None:
        recipe = dataclasses.replace(recipe, sensor_share=float(sensor_share))
    return recipe.draw
