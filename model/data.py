"""ModelNet40 partial-overlap registration protocol (the paper's, vectorised), its extensions, and pairs files.

Protocol (one pair per shape): 1024 points; ``R = Rx Ry Rz`` with each angle uniform in
``[0, max_angle]``; ``t`` uniform in ``[-0.5, 0.5]^3``; ``target = R source + t``; optional Gaussian
noise (sigma 0.01, clipped at +-0.05 as in the authors' code; the paper's text says [-0.5, 0.5]) added
to each cloud independently, before the crop; both clouds cropped to the ``keep`` points nearest to
one far point ``U[0,1)^3 + 500 s (1,1,1)``, ``s = +-1``, the same point for both (applied after
moving the target). Target points are shuffled so that no index correspondence leaks (the authors
shuffle the source too). How this differs from the paper's evaluation: ``docs/ACCURACY.md``.

Settings (:data:`SETTINGS`, :func:`protocol_for`):

* ``clean`` / ``noise`` / ``unseen`` -- the paper's three (``unseen``: train on labels 0-19, test on
  20-39). Source and target are the SAME 1024 points, so the overlap holds exact correspondences.
* ``resampled`` -- source and target are drawn from DISJOINT random halves of a main-file shape's
  1024 points (512 each, ``sampling="disjoint"``), then moved and cropped as above (crop keeps 384
  of 512 = 0.75): no exact correspondences, half the training density. Train and test splits.
* ``dense`` -- two disjoint 1024-point samples of a 4096-point shape of
  ``modelnet40_dense_test.npz`` (test split only: airplane, bathtub, bench), each cropped to 768:
  independent samples at the training density. That file is in the ``modelnet40_normal_resampled``
  axis frame; :func:`load_shapes` maps it to the main files' frame with ``(x, y, z) -> (x, z, y)``
  (:data:`DENSE_TO_MAIN_AXES`). Measured against the same ids of ``modelnet40_test.npz``
  (symmetric Chamfer of the 4096 points vs the 1024, all 170 shapes): median 0.041 airplane /
  0.069 bathtub / 0.054 bench after the swap, 0.49 without (every 7th shape); two disjoint
  1024-point samples of one dense airplane already differ by 0.041. ``(-x, z, y)`` (a proper
  rotation) fits almost as well (these classes are left-right symmetric) but worse on 63% / 74% /
  55% of the shapes, so the plain swap (a reflection) is used.

* ``scans`` -- simulated range scans of the dense test shapes: two disjoint 2048-point samples, each seen by
  its own camera (hidden point removal, :mod:`model.views`: only the surface facing the camera), 512 of the
  visible points each. The cameras stand three shape radii from the centroid, the source's in a random
  direction, the target's turned from it by up to ``view_angle`` (60 degrees by default), so the overlap
  varies from pair to pair and the clouds hold no points behind the visible surface (no ``overlap`` option).

Options of every setting (:func:`protocol_for` keywords; ``mfgnet make-pairs`` / ``evaluate`` /
``train`` flags):

* ``overlap`` -- fraction of each cloud's ``points`` kept by the crop (0.5-1.0); sets ``keep``.
* ``source_points`` / ``target_points`` -- points per cloud after the crop (at most ``keep``): a
  seeded random subset of the crop (same region, lower density), e.g. 384 vs 768 for a density
  mismatch. Counts are fixed per protocol, so every pair of a file has the same shapes.
* ``noise`` -- sigma of the Gaussian noise, clipped at +-5 sigma (the authors' code: 0.01, +-0.05).
* ``max_angle`` -- up to 180 degrees. The rotation stays the paper's per-axis Euler draw (each of
  the three angles uniform in ``[0, max_angle]``, ``R = Rx Ry Rz``), so 45 reproduces the paper
  exactly; beyond 45 the draw is NOT uniform on SO(3) (at 180 the total angle is still spread over
  0-180 degrees but rotations are not Haar-distributed).

With the default options, ``clean`` / ``noise`` / ``unseen`` draw exactly the random numbers they
always did, in the same order, so their pairs are bit-identical for the same seed.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

DATA_ENV = "MFGNET_DATA"
DEFAULT_DATA_DIR = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "modelnet40"
SETTINGS = ("clean", "noise", "unseen", "resampled", "dense", "scans")
UNSEEN_SPLIT_LABEL = 20  # "unseen": train on labels 0-19, test on 20-39
DENSE_FILE = "modelnet40_dense_test.npz"
DENSE_TO_MAIN_AXES = [0, 2, 1]  # (x, y, z) of the dense file -> (x, z, y): the main files' frame
OVERLAP_RANGE = (0.5, 1.0)
OUTLIER_RANGE = (0.0, 0.5)
MAX_ANGLE_LIMIT = 180.0
NOISE_CLIP_SIGMAS = 5.0  # noise is clipped at +-5 sigma (the authors' code's 0.05 for sigma 0.01)


def data_dir(path: str | os.PathLike | None = None) -> Path:
    """ModelNet40 directory: explicit path, else ``$MFGNET_DATA``, else ``../shared/data/modelnet40``."""
    return Path(path or os.environ.get(DATA_ENV) or DEFAULT_DATA_DIR)


def class_names(path: str | os.PathLike | None = None) -> list[str] | None:
    """The class names in label order (ModelNet40's 40, or a ``mfgnet make-dataset`` folder's: one per line, so a name
    may hold spaces), or ``None`` where the data directory lacks them."""
    file = data_dir(path) / "modelnet40_shape_names.txt"
    return [line.strip() for line in file.read_text().splitlines() if line.strip()] if file.exists() else None


@dataclass(frozen=True)
class PairProtocol:
    """Parameters of pair generation (the paper's defaults)."""

    points: int = 1024  # points per cloud before the crop
    keep: int = 768  # points kept by the crop (source and target); overlap = keep / points
    max_angle_deg: float = 45.0
    max_translation: float = 0.5
    noise_sigma: float = 0.0
    noise_clip: float = 0.05
    far_distance: float = 500.0
    # shared: the same points; disjoint: disjoint random subsets; independent: two random subsets (may overlap)
    sampling: Literal["shared", "disjoint", "independent"] = "shared"
    source_points: int | None = None  # points per source after the crop (None: keep)
    target_points: int | None = None  # points per target after the crop (None: keep)
    outliers: float = 0.0  # share of each cloud's points replaced by uniform points in the cloud's bounding box
    # far_point: the paper's crop (the keep points nearest one far point); views: what a camera sees (model.views)
    crop: Literal["far_point", "views"] = "far_point"
    view_angle_deg: float = 60.0  # views: the target's camera turned from the source's by up to this angle

    @property
    def overlap(self) -> float:
        """Fraction of each cloud kept by the crop."""
        return self.keep / self.points

    @property
    def source_count(self) -> int:
        return self.keep if self.source_points is None else self.source_points

    @property
    def target_count(self) -> int:
        return self.keep if self.target_points is None else self.target_points

    def check(self, shape_points: int | None = None) -> None:
        """``ValueError`` when the counts do not fit (optionally for shapes of ``shape_points`` points)."""
        if not 1 <= self.keep <= self.points:
            raise ValueError(f"keep must be in 1..points ({self.points}), got {self.keep}")
        for name, count in (("source_points", self.source_count), ("target_points", self.target_count)):
            if not 1 <= count <= self.keep:
                raise ValueError(f"{name} must be in 1..{self.keep} (the points kept by the crop), got {count}")
        if self.sampling not in SAMPLINGS:
            raise ValueError(f"sampling must be one of {SAMPLINGS}, got {self.sampling!r}")
        if self.crop not in CROPS:
            raise ValueError(f"crop must be one of {CROPS}, got {self.crop!r}")
        if not 0 <= self.view_angle_deg <= MAX_ANGLE_LIMIT:
            raise ValueError(f"view_angle must be in 0..{MAX_ANGLE_LIMIT} degrees, got {self.view_angle_deg}")
        if not OUTLIER_RANGE[0] <= self.outliers <= OUTLIER_RANGE[1]:
            raise ValueError(f"outliers must be in {OUTLIER_RANGE[0]}..{OUTLIER_RANGE[1]}, got {self.outliers}")
        if shape_points is not None:
            needed = self.points * (2 if self.sampling == "disjoint" else 1)
            if shape_points < needed:
                raise ValueError(
                    f"{self.sampling} sampling of {self.points} points per cloud needs {needed} points per shape, "
                    f"got {shape_points}"
                )


SAMPLINGS = ("shared", "disjoint", "independent")
CROPS = ("far_point", "views")

SETTING_PROTOCOLS = {
    "clean": PairProtocol(),
    "noise": PairProtocol(noise_sigma=0.01),
    "unseen": PairProtocol(),
    "resampled": PairProtocol(points=512, keep=384, sampling="disjoint"),
    "dense": PairProtocol(points=1024, keep=768, sampling="disjoint"),
    "scans": PairProtocol(points=2048, keep=512, sampling="disjoint", crop="views"),
}
DENSE_SETTINGS = ("dense", "scans")  # settings drawn from the 4096-point shapes of DENSE_FILE (test split only)


def protocol_for(
    setting: str,
    *,
    source_points: int | None = None,
    target_points: int | None = None,
    overlap: float | None = None,
    noise: float | None = None,
    max_angle: float | None = None,
    points: int | None = None,
    outliers: float | None = None,
    view_angle: float | None = None,
) -> PairProtocol:
    """The protocol of a setting, with optional overrides (``None`` keeps the setting's value).

    ``points`` sets the points per cloud before the crop (the crop keeps the same fraction unless ``overlap``
    is given; ``dense`` shapes have 4096 points, enough for two disjoint clouds of up to 2048);
    ``overlap`` sets ``keep = round(overlap * points)``; ``noise`` sets sigma and a clip of ``5 sigma``;
    ``max_angle`` is in degrees; ``outliers`` replaces that share of each cloud's points (after the crop) by
    points drawn uniformly in the cloud's bounding box (clutter, flying pixels); ``view_angle`` (``scans``) is the
    largest angle in degrees between the source's and the target's camera.
    """
    if setting not in SETTINGS:
        raise ValueError(f"unknown setting {setting!r}; expected one of {SETTINGS}")
    protocol = SETTING_PROTOCOLS[setting]
    changes: dict = {}
    if points is not None:
        if not points >= 1:
            raise ValueError(f"points must be >= 1, got {points}")
        changes["points"], changes["keep"] = int(points), round(protocol.overlap * int(points))
    if overlap is not None:
        if protocol.crop == "views":
            raise ValueError(f"setting {setting!r} crops by views: its overlap follows from view_angle")
        if not OVERLAP_RANGE[0] <= overlap <= OVERLAP_RANGE[1]:
            raise ValueError(f"overlap must be in {OVERLAP_RANGE[0]}..{OVERLAP_RANGE[1]}, got {overlap}")
        changes["keep"] = round(overlap * changes.get("points", protocol.points))
    if noise is not None:
        if not 0 <= noise <= 1:  # inf or NaN (or a sigma beyond the unit ball's shapes) makes non-finite clouds
            raise ValueError(f"noise must be in 0..1 (a sigma in the shapes' unit-ball units), got {noise}")
        changes["noise_sigma"], changes["noise_clip"] = float(noise), NOISE_CLIP_SIGMAS * float(noise)
    if max_angle is not None:
        if not 0 <= max_angle <= MAX_ANGLE_LIMIT:
            raise ValueError(f"max_angle must be in 0..{MAX_ANGLE_LIMIT} degrees, got {max_angle}")
        changes["max_angle_deg"] = float(max_angle)
    if source_points is not None:
        changes["source_points"] = int(source_points)
    if target_points is not None:
        changes["target_points"] = int(target_points)
    if outliers is not None:
        changes["outliers"] = float(outliers)
    if view_angle is not None:
        if protocol.crop != "views":
            raise ValueError(f"view_angle applies to settings that crop by views ('scans'), not {setting!r}")
        changes["view_angle_deg"] = float(view_angle)
    protocol = dataclasses.replace(protocol, **changes)
    protocol.check()
    return protocol


def shapes_file(split: str, setting: str = "clean", path: str | os.PathLike | None = None) -> Path:
    """The ModelNet40 file that holds a split's shapes for a setting (under :func:`data_dir`)."""
    if split not in ("train", "test"):
        raise ValueError(f"split must be 'train' or 'test', got {split!r}")
    if setting not in SETTINGS:
        raise ValueError(f"unknown setting {setting!r}; expected one of {SETTINGS}")
    dense = setting in DENSE_SETTINGS
    if dense and split != "test":
        raise ValueError(f"setting {setting!r} has a test split only ({DENSE_FILE}), got split {split!r}")
    return data_dir(path) / (DENSE_FILE if dense else f"modelnet40_{split}.npz")


class NonFiniteShapesError(ValueError):
    """A ModelNet40 file holds shapes with NaN or infinite coordinates (``rows``: their indices in the file)."""

    def __init__(self, file: Path, rows: np.ndarray, names: np.ndarray | None = None) -> None:
        self.file, self.rows = file, rows
        shown = ", ".join(f"{row} ({names[row]})" if names is not None else str(row) for row in rows[:5])
        more = f" and {len(rows) - 5} more" if len(rows) > 5 else ""
        super().__init__(f"ModelNet40 file {file}: {len(rows)} shape{'s' if len(rows) != 1 else ''} with NaN or "
                         f"infinite coordinates, at index {shown}{more}; remove or repair them")


def load_shapes(split: str, setting: str = "clean",
                path: str | os.PathLike | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Points ``float32 [S, P, 3]`` and labels ``int64 [S]`` of a split for a setting.

    ``P = 1024`` (main files) or 4096 (``dense``, test split only, axes mapped to the main files'
    frame); filtered by label for ``unseen``. A file holding a shape with a NaN or infinite coordinate is refused
    (:class:`NonFiniteShapesError`, naming its index in the file), not trained or evaluated on.
    """
    file = shapes_file(split, setting, path)
    dense = setting in DENSE_SETTINGS
    if not file.exists():
        raise FileNotFoundError(f"ModelNet40 file not found: {file} (set --data or ${DATA_ENV})")
    with np.load(file) as d:
        points, labels = d["points"].astype(np.float32), d["labels"].astype(np.int64)
        bad = np.flatnonzero(~np.isfinite(points).all(axis=tuple(range(1, points.ndim))))  # [S] -> rows
        if len(bad):
            names = d["names"] if "names" in d.files and len(d["names"]) == len(points) else None
            raise NonFiniteShapesError(file, bad, names)
    if dense:
        points = np.ascontiguousarray(points[..., DENSE_TO_MAIN_AXES])
    if setting == "unseen":
        keep = labels < UNSEEN_SPLIT_LABEL if split == "train" else labels >= UNSEEN_SPLIT_LABEL
        points, labels = points[keep], labels[keep]
    return points, labels


def euler_xyz_to_matrix(angles: np.ndarray) -> np.ndarray:
    """``R = Rx(a) Ry(b) Rz(c)`` for ``angles [B, 3]`` in radians -> ``[B, 3, 3]``."""
    cx, cy, cz = np.cos(angles).T
    sx, sy, sz = np.sin(angles).T
    one, zero = np.ones_like(cx), np.zeros_like(cx)
    Rx = np.stack([one, zero, zero, zero, cx, -sx, zero, sx, cx], -1).reshape(-1, 3, 3)
    Ry = np.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy], -1).reshape(-1, 3, 3)
    Rz = np.stack([cz, -sz, zero, sz, cz, zero, zero, zero, one], -1).reshape(-1, 3, 3)
    return Rx @ Ry @ Rz


def crop_nearest_indices(points: np.ndarray, anchor: np.ndarray, keep: int) -> np.ndarray:
    """Indices ``[B, keep]`` (ascending) of the ``keep`` points of ``points [B, N, 3]`` nearest ``anchor [B, 3]``."""
    d2 = ((points - anchor[:, None]) ** 2).sum(-1)  # [B, N]
    idx = np.argpartition(d2, keep - 1, axis=1)[:, :keep]  # [B, keep]
    idx.sort(axis=1)  # keep the stored point order (independent of partition internals)
    return idx


def crop_nearest(points: np.ndarray, anchor: np.ndarray, keep: int) -> np.ndarray:
    """The ``keep`` points of ``points [B, N, 3]`` nearest to ``anchor [B, 3]`` -> ``[B, keep, 3]``."""
    return np.take_along_axis(points, crop_nearest_indices(points, anchor, keep)[..., None], axis=1)


def random_subsets(rng: np.random.Generator, B: int, n: int, size: int) -> np.ndarray:
    """``[B, size]`` random subsets of ``range(n)`` (one per row), in random order."""
    return rng.permuted(np.tile(np.arange(n), (B, 1)), axis=1)[:, :size]


def make_pairs(
    shapes: np.ndarray, protocol: PairProtocol, rng: np.random.Generator, return_indices: bool = False
) -> dict[str, np.ndarray]:
    """One pair per shape of ``shapes [B, P, 3]``; returns source/target/rotation/translation.

    With ``return_indices`` also ``source_index [B, Ns]`` / ``target_index [B, Nt]`` (int64): the row
    of ``shapes[b]`` each source / target point was made from (disjoint for ``sampling="disjoint"``).
    """
    B, P = shapes.shape[:2]
    protocol.check(P)
    N = protocol.points
    if protocol.sampling == "disjoint":
        halves = random_subsets(rng, B, P, 2 * N)  # [B, 2N]
        src_idx, tgt_idx = np.sort(halves[:, :N], axis=1), np.sort(halves[:, N:], axis=1)  # [B, N] each
    elif protocol.sampling == "independent":
        src_idx = np.sort(random_subsets(rng, B, P, N), axis=1)  # [B, N]
        tgt_idx = np.sort(random_subsets(rng, B, P, N), axis=1)  # [B, N], drawn independently
    else:
        src_idx = tgt_idx = np.broadcast_to(np.arange(N), (B, N))  # the same N points
    src = np.take_along_axis(shapes, src_idx[..., None], axis=1).astype(np.float64)  # [B, N, 3]
    tgt = src if protocol.sampling == "shared" else np.take_along_axis(shapes, tgt_idx[..., None], axis=1)
    src_in_shape, tgt_in_shape = src, tgt  # [B, N, 3] each, before the move and the noise: what cameras see
    angles = rng.uniform(0.0, np.deg2rad(protocol.max_angle_deg), size=(B, 3))
    R = euler_xyz_to_matrix(angles)  # [B, 3, 3]
    t = rng.uniform(-protocol.max_translation, protocol.max_translation, size=(B, 3))
    tgt = tgt.astype(np.float64) @ R.transpose(0, 2, 1) + t[:, None]  # [B, N, 3]
    if protocol.noise_sigma > 0:
        clip = protocol.noise_clip
        src = src + np.clip(rng.normal(0, protocol.noise_sigma, src.shape), -clip, clip)
        tgt = tgt + np.clip(rng.normal(0, protocol.noise_sigma, tgt.shape), -clip, clip)
    views = None
    if protocol.crop == "views":
        kept_s, kept_t, views = _view_crops(shapes, src_in_shape, tgt_in_shape, protocol, rng)
    else:
        sign = rng.choice([-1.0, 1.0], size=(B, 1))
        anchor = rng.uniform(0.0, 1.0, size=(B, 3)) + protocol.far_distance * sign  # [B, 3]
        kept_s = crop_nearest_indices(src, anchor, protocol.keep)  # [B, keep] into the N points
        kept_t = crop_nearest_indices(tgt, anchor, protocol.keep)
    if protocol.source_count < protocol.keep:  # lower density: a random subset of the crop
        kept_s = np.take_along_axis(kept_s, np.sort(random_subsets(rng, B, protocol.keep, protocol.source_count), 1), 1)
    if protocol.target_count < protocol.keep:
        kept_t = np.take_along_axis(kept_t, np.sort(random_subsets(rng, B, protocol.keep, protocol.target_count), 1), 1)
    perm = rng.permuted(np.tile(np.arange(protocol.target_count), (B, 1)), axis=1)  # [B, Nt]
    kept_t = np.take_along_axis(kept_t, perm, axis=1)  # shuffled: no index correspondence leaks
    pairs = {
        "source": np.take_along_axis(src, kept_s[..., None], axis=1).astype(np.float32),
        "target": np.take_along_axis(tgt, kept_t[..., None], axis=1).astype(np.float32),
        "rotation": R.astype(np.float32),
        "translation": t.astype(np.float32),
    }
    if return_indices:
        pairs["source_index"] = np.take_along_axis(src_idx, kept_s, axis=1).astype(np.int64)
        pairs["target_index"] = np.take_along_axis(tgt_idx, kept_t, axis=1).astype(np.int64)
        if views is not None:
            pairs.update(views)
    if protocol.outliers > 0:  # drawn last, so pairs without outliers stay bit-identical
        for name in ("source", "target"):
            replaced = add_outliers(pairs[name], protocol.outliers, rng)  # [B, n_out]
            if return_indices:
                np.put_along_axis(pairs[f"{name}_index"], replaced, -1, axis=1)  # no shape point
    return pairs


def _view_crops(shapes: np.ndarray, src: np.ndarray, tgt: np.ndarray, protocol: PairProtocol, rng: np.random.Generator):
    """``crop="views"``: what the source's and the target's camera see of ``src`` / ``tgt`` ``[B, N, 3]`` (in the
    shape's frame, before the move and the noise) -> indices ``[B, keep]`` each and, for ``return_indices``, the
    cameras' unit directions ``source_view`` / ``target_view`` ``[B, 3]`` (shape frame) and ``source_hidden`` /
    ``target_hidden`` ``[B]`` (hidden points filled in where a view shows fewer than ``keep``)."""
    from model.views import view_crop_indices, view_directions  # scipy's convex hull: only this crop needs it

    centres = shapes.mean(axis=1, dtype=np.float64)  # [B, 3]
    radii = np.linalg.norm(shapes - centres[:, None], axis=2).max(axis=1)  # [B]
    source_view, target_view = view_directions(rng, len(shapes), protocol.view_angle_deg)  # [B, 3] each
    kept_s, hidden_s = view_crop_indices(src, centres, radii, source_view, protocol.keep, rng)
    kept_t, hidden_t = view_crop_indices(tgt, centres, radii, target_view, protocol.keep, rng)
    views = {"source_view": source_view, "target_view": target_view, "source_hidden": hidden_s,
             "target_hidden": hidden_t}
    return kept_s, kept_t, views


def add_outliers(clouds: np.ndarray, share: float, rng: np.random.Generator) -> np.ndarray:
    """Replace ``round(share * N)`` random points of each cloud of ``clouds [B, N, 3]`` (in place) by points
    drawn uniformly in that cloud's axis-aligned bounding box; returns their positions ``[B, n_out]``."""
    B, N = clouds.shape[:2]
    count = round(share * N)
    positions = random_subsets(rng, B, N, count)  # [B, count]
    low, high = clouds.min(axis=1, keepdims=True), clouds.max(axis=1, keepdims=True)  # [B, 1, 3] each
    uniform = low + (high - low) * rng.uniform(0.0, 1.0, size=(B, count, 3))  # [B, count, 3]
    np.put_along_axis(clouds, positions[..., None], uniform.astype(clouds.dtype), axis=1)
    return positions


def make_test_pairs(
    setting: str,
    split: str = "test",
    count: int | None = None,
    seed: int = 0,
    path: str | os.PathLike | None = None,
    protocol: PairProtocol | None = None,
    return_indices: bool = False,
) -> dict[str, np.ndarray]:
    """Deterministic pairs of a setting: the same seed gives the same pairs on every machine.

    ``protocol`` replaces the setting's default (e.g. ``protocol_for(setting, max_angle=90)``); the
    setting still picks the shapes. Adds ``label [M]`` and, with ``return_indices``,
    ``shape_index [M]`` (row in the split's file) plus the per-point indices of :func:`make_pairs`.
    """
    shapes, labels = load_shapes(split, setting, path)
    rng = np.random.default_rng(seed)
    rows = np.arange(len(shapes))
    if count is not None and count < len(shapes):
        rows = np.sort(rng.choice(len(shapes), size=count, replace=False))
        shapes, labels = shapes[rows], labels[rows]
    pairs = make_pairs(shapes, protocol or protocol_for(setting), rng, return_indices)
    pairs["label"] = labels
    if return_indices:
        pairs["shape_index"] = rows.astype(np.int64)
    return pairs


PAIR_KEYS = ("source", "target", "rotation", "translation")


def pairs_path(path: str | os.PathLike) -> Path:
    """Where :func:`save_pairs` writes ``path``: numpy adds ``.npz`` to a name that does not end with it."""
    return Path(path) if os.fspath(path).endswith(".npz") else Path(f"{os.fspath(path)}.npz")


ROTATION_TOLERANCE = 1e-4  # a pairs file's rotations: float32 rounding of a proper rotation is far within it


def save_pairs(path: str | os.PathLike, pairs: dict[str, np.ndarray]) -> Path:
    """Write a pairs file: source [M,N,3], target [M,N',3], rotation [M,3,3], translation [M,3]; returns the path
    written (:func:`pairs_path`)."""
    written = pairs_path(path)
    np.savez_compressed(written, **{k: v for k, v in pairs.items() if v is not None})
    return written


def load_pairs(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read and check a pairs file (``target ~= rotation @ source + translation``)."""
    archive = np.load(path, allow_pickle=False)
    if not isinstance(archive, np.lib.npyio.NpzFile):  # an .npy: one array
        raise ValueError(f"pairs file {path} is one array, not an .npz archive of {list(PAIR_KEYS)}")
    with archive as d:
        missing = [k for k in PAIR_KEYS if k not in d.files]
        if missing:
            raise ValueError(f"pairs file {path} lacks {missing}")
        pairs = {k: d[k] for k in d.files}
    M = len(pairs["source"])
    src, tgt = pairs["source"], pairs["target"]
    if src.ndim != 3 or src.shape[-1] != 3 or tgt.ndim != 3 or tgt.shape[-1] != 3 or len(tgt) != M:
        raise ValueError(f"source/target must be [M, N, 3]; got {src.shape} and {tgt.shape}")
    if pairs["rotation"].shape != (M, 3, 3) or pairs["translation"].shape != (M, 3):
        raise ValueError("rotation must be [M, 3, 3] and translation [M, 3]")
    if M == 0:
        raise ValueError(f"pairs file {path} holds no pair")
    for k in PAIR_KEYS:
        finite = np.isfinite(pairs[k].reshape(M, -1)).all(axis=1)  # [M]
        if not finite.all():
            raise ValueError(f"pairs file {path}: {k} of pair {int(np.argmin(finite))} holds NaN or infinite values")
    R = pairs["rotation"].astype(np.float64)  # [M, 3, 3]
    off = np.abs(R.transpose(0, 2, 1) @ R - np.eye(3)).max(axis=(1, 2)) + np.abs(np.linalg.det(R) - 1)  # [M]
    if (off > ROTATION_TOLERANCE).any():
        raise ValueError(f"pairs file {path}: rotation of pair {int(np.argmax(off))} is no rotation (R^T R = I and "
                         f"det R = +1 are off by {off.max():.3g})")
    for k in PAIR_KEYS:
        pairs[k] = pairs[k].astype(np.float32)
    return pairs


ProtocolDraw = Callable[[np.random.Generator], PairProtocol]


class TrainPairStream:
    """Endless random training pairs from a shape array, one fresh pair per shape per epoch.

    ``protocol`` is fixed, or a function drawing one protocol per batch (e.g. :func:`model.recipes.recipe_draw`):
    a :class:`PairProtocol`, or any object with ``make_pairs(shapes, rng)``
    (:class:`model.sensor_pairs.SensorProtocol`).
    """

    def __init__(self, shapes: np.ndarray, protocol: PairProtocol | ProtocolDraw, seed: int):
        self.shapes, self.protocol, self.seed = shapes, protocol, seed

    def batches_per_epoch(self, batch_size: int) -> int:
        return len(self.shapes) // batch_size

    def epoch(self, epoch: int, batch_size: int, first: int = 0,
              shard: tuple[int, int] = (0, 1)) -> Iterator[dict[str, np.ndarray]]:
        """Yield batches (dicts of float32 arrays) of one epoch from batch ``first`` on.

        Batch ``b`` depends only on (seed, epoch, b): the epoch's shape order comes from (seed, epoch), its
        protocol and pair draws from (seed, epoch, b). So a resumed epoch starts at its batch without making
        the ones before, and ``shard = (i, n)`` yields only the batches ``(b - first) % n == i`` (worker ``i`` of
        ``n``: taking one batch from each worker in turn gives the epoch's order).
        """
        order = np.random.default_rng([self.seed, epoch]).permutation(len(self.shapes))
        index, count = shard
        for b in range(first, self.batches_per_epoch(batch_size)):
            if (b - first) % count != index:
                continue
            rng = np.random.default_rng([self.seed, epoch, b])
            protocol = self.protocol if isinstance(self.protocol, PairProtocol) else self.protocol(rng)
            shapes = self.shapes[order[b * batch_size : (b + 1) * batch_size]]
            if isinstance(protocol, PairProtocol):
                yield make_pairs(shapes, protocol, rng)
            else:  # another kind of pair (e.g. model.sensor_pairs.SensorProtocol) makes its own
                yield protocol.make_pairs(shapes, rng)
