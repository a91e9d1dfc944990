"""A folder of one's own shapes (meshes or point clouds) made into a data folder that ``mfgnet train``, ``make-pairs``,
``evaluate`` and ``export`` read as they read ModelNet40's (``mfgnet make-dataset``).

Input: ``SRC/<class>/.../<shape>.<ext>`` (one subfolder per class, searched recursively) or shape files directly in
``SRC`` (one class, named after ``SRC``). A shape file is

* a mesh: ``.obj``, ``.stl``, ``.off``, or ``.ply`` whose header declares faces (read by ``trimesh``, the train
  extra); points are sampled uniformly on its surface (area-weighted);
* a point cloud: any format :func:`service.pointcloud_io.read_points` reads (``.ply`` without faces, ``.pcd``,
  ``.xyz``, ``.npy``, ...); subsampled to the count, at random or by farthest-point sampling.

Files of other suffixes, and hidden ones, are left alone. Each stored shape is centred and scaled as ModelNet40's
are (its ``build.py``, PointNet++'s ``pc_normalize``): the mean of its stored points at the origin, its farthest
point at distance 1 (the unit ball).

Output (the names the commands look for, :func:`model.data.shapes_file`): ``modelnet40_train.npz`` and
``modelnet40_test.npz`` (``points [S, P, 3]``, ``labels int64 [S]``, ``names [S]``, ``class_names [K]``; rows sorted
by label, then name), ``modelnet40_dense_test.npz`` (the test shapes again with ``dense_points`` points each, for the
``dense`` and ``scans`` settings; stored with y and z swapped, as ModelNet40's dense file is, since
:func:`model.data.load_shapes` swaps them back), ``modelnet40_shape_names.txt`` (the class names in label order, as
:func:`model.data.class_names` reads them) and ``dataset.json`` (what was made, from what, with which options).

Every random draw is seeded by ``seed`` and the shape's (or class's) name, so one shape's points and one class's split
do not change when other shapes are added or left out.
"""

from __future__ import annotations

import json
import os
import zlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from model.data import DENSE_FILE, DENSE_TO_MAIN_AXES, UNSEEN_SPLIT_LABEL
from service.formats import READ_SUFFIXES

MESH_SUFFIXES = (".obj", ".stl", ".off")  # and .ply where its header declares faces
SHAPE_SUFFIXES = tuple(sorted(set(MESH_SUFFIXES) | set(READ_SUFFIXES)))
SUBSAMPLINGS = ("random", "fps")
DTYPES = ("float32", "float16")
DEFAULT_POINTS = 1024  # as ModelNet40's files
DEFAULT_DENSE_POINTS = 4096  # as ModelNet40's dense file: two disjoint 2048-point clouds for the scans setting
DEFAULT_TEST_FRACTION = 0.2  # ModelNet40's official split holds out 2468 of 12311 shapes (20%)
OUTPUT_FILES = ("modelnet40_train.npz", "modelnet40_test.npz", DENSE_FILE, "modelnet40_shape_names.txt", "dataset.json")
PLY_HEADER_BYTES = 1 << 16  # a PLY header longer than this is taken as no mesh's


class DatasetError(ValueError):
    """The source folder or the options cannot make a data folder (a usage error naming the problem)."""


class BadShapeError(ValueError):
    """One shape file cannot be used: unreadable, no faces, zero area, NaN coordinates, too few points."""


@dataclass(frozen=True)
class ShapeFile:
    """A shape file of the source folder: ``name`` (its path below the folder, with ``/``) and its class."""

    name: str
    path: Path
    class_name: str


@dataclass
class Shape:
    """A shape as read: a mesh (``vertices [V, 3]``, ``faces [F, 3]``) or a cloud (``faces`` None)."""

    vertices: np.ndarray
    faces: np.ndarray | None = None


@dataclass
class Dataset:
    """What :func:`build_dataset` wrote: the shapes of each split, those left out (name -> why) and the files."""

    classes: list[str]
    train: list[str]
    test: list[str]
    dense: list[str]
    skipped: dict[str, str] = field(default_factory=dict)
    ignored: int = 0
    files: list[Path] = field(default_factory=list)


def is_shape_file(path: Path) -> bool:
    return path.suffix.lower() in SHAPE_SUFFIXES and not path.name.startswith(".")


def find_shapes(src: Path) -> tuple[list[ShapeFile], int]:
    """The shape files of ``src`` (sorted by class, then name) and the count of other files left alone.

    ``src`` with subfolders: each is a class (files of shape suffixes beside them are refused); else its files are
    one class named after it. Raises :class:`DatasetError` for an empty folder or an empty class folder."""
    if not src.is_dir():
        raise DatasetError(f"{src}: {'no such folder' if not src.exists() else 'not a folder'}")
    entries = sorted(p for p in src.iterdir() if not p.name.startswith("."))
    folders = [p for p in entries if p.is_dir()]
    if not folders:
        shapes = [ShapeFile(p.name, p, src.resolve().name) for p in entries if p.is_file() and is_shape_file(p)]
        if not shapes:
            raise DatasetError(f"{src}: no shape files (suffixes {' '.join(SHAPE_SUFFIXES)}) and no class folders")
        return shapes, len(entries) - len(shapes)
    beside = [p.name for p in entries if p.is_file() and is_shape_file(p)]
    if beside:
        raise DatasetError(
            f"{src}: shape files beside the class folders ({', '.join(beside[:3])}"
            f"{' ...' if len(beside) > 3 else ''}); put each in its class's folder"
        )
    shapes, ignored = [], 0
    for folder in folders:
        found = []
        for root, dirs, files in os.walk(folder):
            dirs[:] = sorted(d for d in dirs if not d.startswith("."))
            for name in sorted(files):
                path = Path(root) / name
                if is_shape_file(path):
                    found.append(ShapeFile(path.relative_to(src).as_posix(), path, folder.name))
                else:
                    ignored += 1
        if not found:
            raise DatasetError(f"class folder {folder}: no shape files (suffixes {' '.join(SHAPE_SUFFIXES)})")
        shapes.extend(sorted(found, key=lambda s: s.name))
    return shapes, ignored


def ply_has_faces(path: Path) -> bool:
    """Whether the PLY file's header declares at least one face (a mesh), read without a PLY library."""
    with open(path, "rb") as f:
        head = f.read(PLY_HEADER_BYTES)
    end = head.find(b"end_header")
    for line in head[: end if end >= 0 else len(head)].decode("ascii", "replace").splitlines():
        words = line.split()
        if len(words) == 3 and words[:2] == ["element", "face"] and words[2].isdigit():
            return int(words[2]) > 0
    return False


def read_mesh(path: Path) -> Shape:
    """The vertices and triangles of a mesh file (``trimesh``, the train extra)."""
    try:
        import trimesh
    except ImportError as err:
        raise DatasetError(f"{path}: reading meshes needs trimesh, of the train extra ({err})") from err
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # any parser error of trimesh's loaders: the file is unreadable
        raise BadShapeError(f"not a readable mesh ({type(err).__name__}: {str(err)[:120]})") from err
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64)
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64)
    if len(faces) == 0:
        raise BadShapeError("no faces (not a mesh, or an unreadable one)")
    return Shape(vertices, faces)


def read_shape(path: Path) -> Shape:
    """The mesh or point cloud in ``path``; :class:`BadShapeError` when it cannot be used."""
    from service.pointcloud_io import PointCloudFormatError, read_points

    suffix = path.suffix.lower()
    try:
        if suffix in MESH_SUFFIXES or (suffix == ".ply" and ply_has_faces(path)):
            return read_mesh(path)
        return Shape(read_points(path))
    except PointCloudFormatError as err:
        raise BadShapeError(str(err).replace(f"{path}: ", "").replace(f"{path.name}: ", "")) from err
    except OSError as err:
        raise BadShapeError(f"cannot read it ({err.strerror or err})") from err


def sample_surface(shape: Shape, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` points ``[count, 3]`` uniform on the mesh's surface (each triangle drawn in proportion to its area)."""
    import trimesh

    corners = shape.vertices[shape.faces]  # [F, 3, 3]
    if not np.isfinite(corners).all():
        raise BadShapeError("NaN or infinite vertex coordinates")
    area = float(np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum())
    if not area > 0 or not np.isfinite(area):
        raise BadShapeError(f"zero surface area ({len(shape.faces)} degenerate faces)")
    mesh = trimesh.Trimesh(shape.vertices, shape.faces, process=False)
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=rng)
    return np.asarray(points, dtype=np.float64)


def farthest_points(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Indices ``[count]`` of a farthest-point sample of ``points [N, 3]`` from a random first point."""
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = rng.integers(len(points))
    nearest = np.linalg.norm(points - points[chosen[0]], axis=1)  # [N] distance to the chosen set
    for i in range(1, count):
        chosen[i] = int(np.argmax(nearest))
        nearest = np.minimum(nearest, np.linalg.norm(points - points[chosen[i]], axis=1))
    return chosen


def sample_shape(shape: Shape, count: int, rng: np.random.Generator, subsample: str = "random") -> np.ndarray:
    """``count`` points ``[count, 3]`` of a shape: sampled on a mesh's surface, or a subset of a cloud's points
    (``random``: a random subset in stored order, as ModelNet40's build; ``fps``: farthest-point sampling)."""
    if shape.faces is not None:
        return sample_surface(shape, count, rng)
    points = shape.vertices
    if len(points) < count:
        raise BadShapeError(f"{len(points)} points, fewer than the {count} asked for")
    if subsample == "fps":
        return points[np.sort(farthest_points(points, count, rng))]
    return points[np.sort(rng.choice(len(points), count, replace=False))]


def normalise(points: np.ndarray) -> np.ndarray:
    """``points [N, 3]`` with their mean at the origin and their farthest point at distance 1 (ModelNet40's)."""
    centred = points - points.mean(axis=0)
    radius = float(np.linalg.norm(centred, axis=1).max())
    if not radius > 1e-12 * max(1.0, float(np.abs(points).max())):
        raise BadShapeError("all its points at one place (a degenerate shape)")
    return centred / radius


def name_seed(seed: int, name: str, stream: int = 0) -> np.random.Generator:
    """The generator of ``name``'s draws: depends on the seed and the name only (and the stream: 0 main, 1 dense)."""
    return np.random.default_rng([seed, zlib.crc32(name.encode()), stream])


def split_test(
    classes: dict[str, list[str]], seed: int, test_fraction: float | None, test_names: set[str] | None
) -> set[str]:
    """The names of the test shapes: those of ``test_names`` (a split file), else ``round(test_fraction x n)`` of
    each class's ``n`` shapes (at least 1 and at most ``n - 1``), drawn with the class's seed. Every class must keep
    shapes in both splits (:class:`DatasetError`)."""
    test: set[str] = set()
    for class_name, names in classes.items():
        if test_names is not None:
            chosen = [n for n in names if n in test_names]
        else:
            if len(names) < 2:
                raise DatasetError(
                    f"class {class_name!r}: {len(names)} usable shape"
                    f"{'s' if len(names) != 1 else ''}; each class needs at least 2 (one for each "
                    "split)"
                )
            k = min(max(1, round(test_fraction * len(names))), len(names) - 1)
            rng = np.random.default_rng([seed, zlib.crc32(class_name.encode()), 2])
            chosen = [names[i] for i in np.sort(rng.choice(len(names), k, replace=False))]
        if not chosen or len(chosen) == len(names):
            which = "train" if chosen else "test"
            raise DatasetError(
                f"class {class_name!r}: no {which} shapes (the split file names {len(chosen)} of its "
                f"{len(names)} usable shapes as test); each class needs shapes in both splits"
            )
        test.update(chosen)
    return test


def read_split_file(path: Path, known: Iterable[str]) -> set[str]:
    """The test shapes' names in a split file (one per line, as ``dataset.json`` and the ``names`` arrays give them:
    the path below the source folder; blank lines and ``#`` comments skipped); names it does not know are refused."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise DatasetError(f"--split-file {path}: cannot read ({getattr(err, 'strerror', None) or err})") from err
    names = {line.strip() for line in lines if line.strip() and not line.strip().startswith("#")}
    unknown = sorted(names - set(known))
    if unknown:
        raise DatasetError(
            f"--split-file {path}: {len(unknown)} name{'s' if len(unknown) != 1 else ''} of no shape "
            f"file in the source folder: {', '.join(unknown[:3])}{' ...' if len(unknown) > 3 else ''}"
            " (names are paths below the source folder, e.g. chair/a.obj)"
        )
    if not names:
        raise DatasetError(f"--split-file {path}: names no test shape")
    return names


def save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """``arrays`` into ``path`` as ModelNet40's files are (``np.savez_compressed``), written beside and renamed."""
    partial = path.with_name(f".{path.name}.partial.npz")
    np.savez_compressed(partial, **arrays)
    os.replace(partial, path)


def split_arrays(
    points: list[np.ndarray], names: list[str], labels: list[int], classes: list[str], dtype: str
) -> dict[str, np.ndarray]:
    return {
        "points": np.stack(points).astype(dtype),
        "labels": np.asarray(labels, dtype=np.int64),
        "names": np.asarray(names, dtype=np.str_),
        "class_names": np.asarray(classes, dtype=np.str_),
    }


def build_dataset(
    src: Path,
    out: Path,
    *,
    points: int = DEFAULT_POINTS,
    dense_points: int = DEFAULT_DENSE_POINTS,
    seed: int = 0,
    test_fraction: float | None = DEFAULT_TEST_FRACTION,
    split_file: Path | None = None,
    dtype: str = "float32",
    subsample: str = "random",
    skip_bad: bool = False,
    progress: Callable[[Iterable, str], Iterable] | None = None,
) -> Dataset:
    """Read, sample, normalise and split the shapes of ``src``; write the data folder ``out`` (which must exist).

    A shape that cannot be used raises :class:`DatasetError` naming it, or with ``skip_bad`` is left out (listed in
    ``Dataset.skipped`` and ``dataset.json``). ``dense_points`` 0 writes no dense file; a cloud of fewer points than
    ``dense_points`` is left out of the dense file only."""
    progress = progress or (lambda items, _: items)
    files, ignored = find_shapes(src)
    test_names = read_split_file(split_file, (f.name for f in files)) if split_file is not None else None
    main: dict[str, np.ndarray] = {}
    skipped: dict[str, str] = {}
    for file in progress(files, "shapes"):
        try:
            main[file.name] = normalise(
                sample_shape(read_shape(file.path), points, name_seed(seed, file.name), subsample)
            )
        except BadShapeError as err:
            if not skip_bad:
                raise DatasetError(f"{file.path}: {err} (--skip-bad leaves such shapes out)") from err
            skipped[file.name] = str(err)
    classes = sorted({f.class_name for f in files})
    by_class = {c: [f.name for f in files if f.class_name == c and f.name in main] for c in classes}
    test = split_test(by_class, seed, test_fraction, test_names)
    label = {f.name: classes.index(f.class_name) for f in files}
    dataset = Dataset(classes, [n for n in main if n not in test], [n for n in main if n in test], [], skipped, ignored)
    order = sorted(main, key=lambda n: (label[n], n))
    for split, names in (("train", set(dataset.train)), ("test", test)):
        rows = [n for n in order if n in names]
        path = out / f"modelnet40_{split}.npz"
        save_npz(path, split_arrays([main[n] for n in rows], rows, [label[n] for n in rows], classes, dtype))
        dataset.files.append(path)
    dense_skipped: dict[str, str] = {}
    if dense_points:
        dense: dict[str, np.ndarray] = {}
        paths = {f.name: f.path for f in files}
        for name in progress([n for n in order if n in test], "dense test shapes"):
            try:  # the test shapes read again: only they are kept at this density
                dense[name] = normalise(
                    sample_shape(read_shape(paths[name]), dense_points, name_seed(seed, name, 1), subsample)
                )
            except BadShapeError as err:  # read once already: only a cloud of too few points fails here
                dense_skipped[name] = str(err)
        dataset.dense = list(dense)
        if dense:
            arrays = split_arrays(
                [p[:, DENSE_TO_MAIN_AXES] for p in dense.values()],
                list(dense),
                [label[n] for n in dense],
                classes,
                dtype,
            )
            save_npz(out / DENSE_FILE, arrays)
            dataset.files.append(out / DENSE_FILE)
    names_file = out / "modelnet40_shape_names.txt"
    names_file.write_text("".join(f"{c}\n" for c in classes))
    record = {
        "source": str(src.resolve()),
        "classes": {
            c: {
                "label": i,
                "train": sum(n in by_class[c] for n in dataset.train),
                "test": sum(n in by_class[c] for n in dataset.test),
            }
            for i, c in enumerate(classes)
        },
        "points": points,
        "dense_points": dense_points,
        "dense_shapes": len(dataset.dense),
        "seed": seed,
        "split": {"split_file": str(split_file)} if split_file is not None else {"test_fraction": test_fraction},
        "dtype": dtype,
        "subsample": subsample,
        "normalised": "each shape's stored points: mean at the origin, farthest point at distance 1",
        "dense_axes": "stored with y and z swapped (ModelNet40's dense frame); mfgnet swaps them back on loading",
        "unseen": unseen_note(classes),
        "skipped": skipped,
        "not_dense": dense_skipped,
    }
    (out / "dataset.json").write_text(json.dumps(record, indent=2) + "\n")
    dataset.files += [names_file, out / "dataset.json"]
    return dataset


def unseen_note(classes: list[str]) -> str:
    """What the ``unseen`` setting (train on labels below :data:`UNSEEN_SPLIT_LABEL`, test on the rest) does here."""
    if len(classes) <= UNSEEN_SPLIT_LABEL:
        return (
            f"not available: the unseen setting tests on labels {UNSEEN_SPLIT_LABEL} and up, and this set has "
            f"{len(classes)} class{'es' if len(classes) != 1 else ''}"
        )
    return (
        f"trains on labels 0-{UNSEEN_SPLIT_LABEL - 1} ({classes[0]} ... {classes[UNSEEN_SPLIT_LABEL - 1]}), tests "
        f"on {UNSEEN_SPLIT_LABEL}-{len(classes) - 1} ({classes[UNSEEN_SPLIT_LABEL]} ... {classes[-1]})"
    )
