"""Training pairs that look like real scans: two simulated sensor views (:mod:`model.sensor_sim`) of one object or of
one room-like scene, at any relative orientation, sampled to fixed point counts.

* ``object`` pairs: a ModelNet40 shape (densified), seen by two cameras 2-4 shape radii away, the target's turned
  from the source's by up to ``view_angle_deg`` (range-image pairs of one object, as the Stanford scans).
* ``scene`` pairs: several shapes of the batch standing on a floor with one or two walls, seen by two cameras at
  head height a baseline apart, each with a cone of view (partial, partially overlapping room fragments).

Each pair is then put in a random orientation (Haar-uniform) and scaled by one common factor so that the source's
RMS radius is ``radius``; the target is moved by ``R`` (angle up to ``max_angle_deg``, axis uniform) and ``t``
(uniform in ``[-max_translation, max_translation]^3``): ``target = R source + t``, target points shuffled. Counts
are fixed per protocol (``source_points``, ``target_points``): ``sampling="random"`` draws a random subset (the
sensor's density kept), ``"spread"`` the runtime's own resampling (:func:`service.sampling.resample_indices`,
farthest-point sampling).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation

from model.sensor_sim import SensorEffects, densify, estimate_normals, scan

UP = 2  # z is up in the ModelNet40 files (tall classes such as bottles are long along z)
OBJECT_DENSIFY = 6  # 1024-point shapes -> 6144 before a view of about a third of them is thinned
SCENE_DENSIFY = 1  # objects of 0.25-0.6 m radius: 1024 points are already denser than the planes
PLANE_DENSITY = (150.0, 300.0)  # points per square metre on the floor and walls
KINDS = ("object", "scene")
MIN_VIEW_POINTS = 64  # scenes: a camera pair whose views hold fewer points is drawn again ...
SCENE_CAMERA_TRIES = 10  # ... up to this many times, then once more without the cone of view
SAMPLINGS = ("random", "spread")


@dataclass(frozen=True)
class SensorProtocol:
    """One batch's sensor-pair parameters (every pair of the batch has the same counts)."""

    kind: Literal["object", "scene"] = "object"
    source_points: int = 512
    target_points: int = 512
    max_angle_deg: float = 180.0
    max_translation: float = 0.5
    view_angle_deg: float = 75.0  # object: the target's camera turned from the source's by up to this angle
    radius: float = 0.5  # the source's RMS radius after scaling
    sampling: Literal["random", "spread"] = "random"
    effects: SensorEffects = field(default_factory=SensorEffects)

    def check(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {self.kind!r}")
        if self.sampling not in SAMPLINGS:
            raise ValueError(f"sampling must be one of {SAMPLINGS}, got {self.sampling!r}")
        if not 0 <= self.max_angle_deg <= 180:
            raise ValueError(f"max_angle must be in 0..180 degrees, got {self.max_angle_deg}")
        if min(self.source_points, self.target_points) < 1:
            raise ValueError("point counts must be positive")

    def make_pairs(self, shapes: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
        """One pair per shape of ``shapes [B, P, 3]`` (scenes also borrow other shapes of the batch)."""
        return sensor_pairs(shapes, self, rng)


def random_rotations(rng: np.random.Generator, count: int, max_angle_deg: float) -> np.ndarray:
    """``[count, 3, 3]`` rotations about uniform axes by angles up to ``max_angle_deg`` with the Haar measure's
    angle density ``(1 - cos a) / pi`` (at 180: Haar-uniform on SO(3))."""
    grid = np.linspace(0.0, np.deg2rad(max_angle_deg), 2049)
    cdf = grid - np.sin(grid)  # proportional to the Haar angle distribution's CDF
    if cdf[-1] <= 0:
        return np.broadcast_to(np.eye(3), (count, 3, 3)).copy()
    angle = np.interp(rng.uniform(0.0, cdf[-1], count), cdf, grid)  # [count]
    axis = rng.standard_normal((count, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return Rotation.from_rotvec(axis * angle[:, None]).as_matrix()


def sample_to_count(points: np.ndarray, count: int, sampling: str, rng: np.random.Generator) -> np.ndarray:
    """Exactly ``count`` rows of ``points [N, 3]``; where ``N < count`` all of them and jittered repeats."""
    if len(points) == 0:
        raise ValueError("a view holds no points")
    if len(points) < count:
        extra = points[rng.integers(0, len(points), count - len(points))]
        scale = 1e-3 * float(np.ptp(points, axis=0).max() or 1.0)
        return np.vstack([points, extra + rng.normal(0.0, scale, extra.shape)])
    if sampling == "spread":
        from service.sampling import resample_indices

        return points[resample_indices(points, count)]
    return points[rng.choice(len(points), size=count, replace=False)]


def look_at(camera: np.ndarray, target: np.ndarray) -> np.ndarray:
    d = target - camera
    return d / np.linalg.norm(d)


def _object_views(shape: np.ndarray, normals: np.ndarray, protocol: SensorProtocol, rng: np.random.Generator):
    """The two scans of one object (shape frame)."""
    from model.views import view_directions

    pts, nrm = densify(shape, normals, OBJECT_DENSIFY, rng)
    centre = pts.mean(axis=0)
    radius = np.linalg.norm(pts - centre, axis=1).max()
    src_dir, tgt_dir = view_directions(rng, 1, protocol.view_angle_deg)  # [1, 3] each
    views = []
    for direction in (src_dir[0], tgt_dir[0]):
        camera = centre + rng.uniform(2.0, 4.0) * radius * direction
        aim = centre + rng.normal(0.0, 0.1 * radius, 3)
        views.append(scan(pts, nrm, camera, look_at(camera, aim), protocol.effects, rng))
    return views


def _plane(rng: np.random.Generator, origin: tuple[float, float, float], u: tuple[float, float, float],
           v: tuple[float, float, float], normal: tuple[float, float, float], density: float):
    """Uniform points on the parallelogram ``origin + a u + b v`` (``a, b`` in [0, 1]) and its normals."""
    u, v = np.asarray(u, float), np.asarray(v, float)
    count = max(16, round(density * np.linalg.norm(np.cross(u, v))))
    ab = rng.random((count, 2))
    pts = np.asarray(origin, float) + ab[:, :1] * u + ab[:, 1:] * v
    return pts, np.broadcast_to(np.asarray(normal, float), pts.shape)


def build_scene(objects: list[np.ndarray], object_normals: list[np.ndarray],
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """A room corner: ``objects`` (``[P, 3]`` each, any scale) scaled to 0.25-0.6 m radius, turned about the
    vertical, standing apart on a floor ``[-L, L]^2`` (``L`` 1.5-2.5 m) with a wall along ``y = L`` and perhaps one
    along ``x = L``. Returns points ``[N, 3]``, normals ``[N, 3]``, the floor's half size, and the objects' centres
    ``[K, 3]``."""
    half = rng.uniform(1.5, 2.5)
    density = rng.uniform(*PLANE_DENSITY)
    pts, nrm, centres, footprints = [], [], [], []
    for shape, normals in zip(objects, object_normals, strict=True):
        s, n = densify(shape, normals, SCENE_DENSIFY, rng)
        s = s - s.mean(axis=0)
        r = rng.uniform(0.25, 0.6)
        s *= r / np.linalg.norm(s, axis=1).max()
        yaw = Rotation.from_euler("z", rng.uniform(0, 2 * np.pi)).as_matrix()
        s, n = s @ yaw.T, n @ yaw.T
        for _ in range(20):  # a free spot on the floor (objects apart), else the last try
            xy = rng.uniform(-0.6 * half, 0.6 * half, 2)
            if all(np.linalg.norm(xy - c) > r + rr for c, rr in footprints):
                break
        footprints.append((xy, r))
        s = s + np.r_[xy, -s[:, UP].min()]  # standing on the floor z = 0
        pts.append(s)
        nrm.append(n)
        centres.append(s.mean(axis=0))
    height = rng.uniform(2.2, 2.8)
    planes = [_plane(rng, (-half, -half, 0), (2 * half, 0, 0), (0, 2 * half, 0), (0, 0, 1), density),
              _plane(rng, (-half, half, 0), (2 * half, 0, 0), (0, 0, height), (0, -1, 0), density)]
    if rng.random() < 0.5:
        planes.append(_plane(rng, (half, -half, 0), (0, 2 * half, 0), (0, 0, height), (-1, 0, 0), density))
    for p, n in planes:
        pts.append(p)
        nrm.append(n)
    return np.vstack(pts), np.vstack(nrm), half, np.array(centres)


def _scene_views(objects: list[np.ndarray], object_normals: list[np.ndarray], protocol: SensorProtocol,
                 rng: np.random.Generator):
    """The two scans of one room-like scene (room frame): cameras on the open side, looking in and down, a baseline
    apart. Camera pairs whose views hold fewer than ``MIN_VIEW_POINTS`` points are drawn again (at last without
    the cone of view)."""
    pts, nrm, half, centres = build_scene(objects, object_normals, rng)
    effects = protocol.effects
    for attempt in range(SCENE_CAMERA_TRIES + 1):
        if attempt == SCENE_CAMERA_TRIES:
            effects = dataclasses.replace(effects, half_angle_deg=180.0)
        phi = rng.uniform(np.deg2rad(190), np.deg2rad(260))  # away from the walls at +x / +y
        height = rng.uniform(1.0, 1.8)
        camera = np.r_[rng.uniform(0.9, 1.3) * half * np.array([np.cos(phi), np.sin(phi)]), height]
        aim = centres[rng.integers(len(centres))] + rng.normal(0.0, 0.3, 3)
        baseline = rng.normal(size=3) * [1, 1, 0.2]
        camera2 = camera + rng.uniform(0.3, 1.2) * baseline / np.linalg.norm(baseline)
        aim2 = aim + rng.normal(0.0, 0.5, 3)
        views = []
        for c, a in ((camera, aim), (camera2, aim2)):
            a = np.r_[a[:2], np.clip(a[2], 0.0, min(1.0, c[2] - 0.3))]  # looking down into the room
            views.append(scan(pts, nrm, c, look_at(c, a), effects, rng))
        if min(len(v) for v in views) >= MIN_VIEW_POINTS:
            break
    return views


def sensor_pairs(shapes: np.ndarray, protocol: SensorProtocol, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """One sensor pair per shape of ``shapes [B, P, 3]``: ``source [B, Ns, 3]``, ``target [B, Nt, 3]``,
    ``rotation [B, 3, 3]``, ``translation [B, 3]`` (float32; ``target = R source + t``)."""
    protocol.check()
    B = len(shapes)
    shapes = shapes.astype(np.float64)
    normals = [estimate_normals(s) for s in shapes]
    R = random_rotations(rng, B, protocol.max_angle_deg)  # [B, 3, 3]
    t = rng.uniform(-protocol.max_translation, protocol.max_translation, (B, 3))
    frames = random_rotations(rng, B, 180.0)  # each pair's sensor frame: any orientation
    src_out = np.empty((B, protocol.source_points, 3), np.float32)
    tgt_out = np.empty((B, protocol.target_points, 3), np.float32)
    for b in range(B):
        if protocol.kind == "object":
            src, tgt = _object_views(shapes[b], normals[b], protocol, rng)
        else:
            others = rng.permutation(np.delete(np.arange(B), b))[: rng.integers(1, 4)] if B > 1 else []
            members = [b, *others]
            src, tgt = _scene_views([shapes[i] for i in members], [normals[i] for i in members], protocol, rng)
        src = sample_to_count(src, protocol.source_points, protocol.sampling, rng)
        tgt = sample_to_count(tgt, protocol.target_points, protocol.sampling, rng)
        centre = src.mean(axis=0)
        scale = protocol.radius / np.sqrt(((src - centre) ** 2).sum(axis=1).mean())
        src = (src - centre) * scale @ frames[b].T  # [Ns, 3]
        tgt = (tgt - centre) * scale @ frames[b].T
        src_out[b] = src
        tgt_out[b] = rng.permutation(tgt @ R[b].T + t[b])  # shuffled: no index correspondence leaks
    return {"source": src_out, "target": tgt_out, "rotation": R.astype(np.float32),
            "translation": t.astype(np.float32)}


def validation_pairs(shapes: np.ndarray, seed: int, counts: int = 512, chunk: int = 16,
                     max_angle_deg: float = 180.0) -> dict[str, np.ndarray]:
    """Seeded sensor pairs for choosing checkpoints: chunks of ``chunk`` shapes, object and scene pairs in turn,
    rotations up to ``max_angle_deg`` (default: any orientation), ``counts`` points per cloud, the runtime's spread
    sampling."""
    rng = np.random.default_rng([seed, 7, 28])
    parts = []
    for i, start in enumerate(range(0, len(shapes), chunk)):
        protocol = SensorProtocol(kind=KINDS[i % 2], source_points=counts, target_points=counts, sampling="spread",
                                  max_angle_deg=max_angle_deg)
        parts.append(sensor_pairs(shapes[start : start + chunk], protocol, rng))
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
