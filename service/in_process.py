"""Registration inside the caller's process (a ROS node, a scanning app): the answer ``POST /v1/register`` and
``mfgnet register`` give for the same clouds and options, without HTTP.

    >>> registrar = LocalRegistrar("general")           # loads and warms the model once
    >>> result = registrar.register(source, target)     # arrays [N, 3] or point-cloud files
    >>> result.transform                                 # [4, 4] src_to_tgt: target ~= source @ R.T + t

Options left out get the service's request defaults (:func:`service.request_defaults.request_defaults`: ``refine``
``"icp-plane"``, ``rotation_search`` ``"auto"`` for refined requests), as the server applies them with its default
settings; the bare :meth:`service.registrar.Registrar.register` runs the paper's pipeline instead (no refinement).
"""

from __future__ import annotations

import numbers
import os
from pathlib import Path
from typing import Any

from numpy.typing import ArrayLike

from service.errors import InputError
from service.manifest import Manifest, bundled_models_dir
from service.options import check_flag
from service.registrar import Registrar
from service.request_defaults import DEFAULT_MODEL, THREAD_RANGE, request_defaults
from service.result import RegistrationResult

Cloud = ArrayLike | str | os.PathLike[str]  # an [N, 3] array-like of numbers, or a point-cloud file


class LocalRegistrar:
    """One model loaded (sha256-verified) in this process, registering with the service's request defaults.

    ``model``: a bundled model's name (``"general"``, ``"clean"``, ...), or a model folder (a ``Path``, or a ``str``
    that names no bundled model). ``threads``: ONNX Runtime threads per graph (default: up to 2, as the server's
    ``MFGNET_THREADS``); the pose does not depend on it. ``warmup``: register a synthetic pair now, so that the
    first call does not pay for allocations.

    Thread safety: one instance may be shared by threads, as the server shares one per model among its worker
    threads; concurrent calls give the results of sequential ones. Build it on the main thread: it sets numpy's BLAS
    to one thread for the whole process (:mod:`service.blas_threads`), which OpenBLAS only takes from the main thread
    (built on another, it gives the same poses, more slowly under load; ``OMP_NUM_THREADS=1`` does the same).

    Raises:
        ValueError: ``model`` names no bundled model and no folder, or ``threads`` is no whole number in
            ``THREAD_RANGE`` (1..64, as ``mfgnet register --threads``).
        service.manifest.ModelIntegrityError: the model's files are missing or do not match its manifest.
    """

    def __init__(self, model: str | Path = DEFAULT_MODEL, *, threads: int | None = None, warmup: bool = True):
        self.registrar = Registrar(model_directory(model), threads=checked_threads(threads), warmup=warmup)

    @property
    def manifest(self) -> Manifest:
        """The loaded model's manifest: ``name``, ``version``, ``sha256`` (as a response's ``model``)."""
        return self.registrar.manifest

    def register(self, source: Cloud, target: Cloud, **options: Any) -> RegistrationResult:
        """Register ``source`` onto ``target``: ``result.transform`` is the ``[4, 4]`` ``src_to_tgt`` pose
        (``target ~= source @ R.T + t``), in the clouds' units; ``result.reliable`` and ``result.warnings`` say
        whether to trust it, ``result.timing_ms`` how long each stage took.

        ``source`` ``[N, 3]``, ``target`` ``[M, 3]`` (N, M >= 32; any numeric dtype, used as float64), or paths of
        point-cloud files (``.ply .pcd .las .laz .e57 .xyz .txt .csv .pts .ptx .npy .npz``, read by
        :func:`service.pointcloud_io.read_points`). ``options``: the fields of
        :class:`service.options.RegistrationOptions` (``refine``, ``rotation_search``, ``keypoints``,
        ``initial_transform`` as a 4x4 ``src_to_tgt``, ...); ``refine`` and ``rotation_search`` left out or ``None``
        get the service's defaults. ``return_correspondences`` (the HTTP API's) is taken and changes nothing: the
        result always holds the correspondences.

        Raises:
            service.errors.InputError: a bad cloud or option (the server's 422), naming it.
            service.pointcloud_io.PointCloudFormatError: an unreadable file; ``OSError``: a file that cannot be
                opened.
        """
        if "options" in options:  # Registrar.register's RegistrationOptions: its refine=None would mean "none"
            raise TypeError("LocalRegistrar.register takes options as keywords (refine=..., keypoints=...)")
        known = Registrar.option_names | {"return_correspondences"}
        if unknown := sorted(set(options) - known):  # the server's 422, not RegistrationOptions' TypeError
            hint = "; the model is chosen by LocalRegistrar(model)" if "model" in unknown else ""
            raise InputError(f"unknown option{'s' if len(unknown) > 1 else ''} {', '.join(unknown)} (options: "
                             f"{', '.join(sorted(known))}){hint}")
        if "return_correspondences" in options:  # the HTTP option; a result in process always holds them
            check_flag(options.pop("return_correspondences"), "return_correspondences")
        refine, rotation_search = request_defaults(options.pop("refine", None), options.pop("rotation_search", None))
        return self.registrar.register(read_cloud(source), read_cloud(target), refine=refine,
                                       rotation_search=rotation_search, **options)


def model_directory(model: str | Path) -> Path:
    """The folder of ``model``: a ``Path`` as it is; a ``str`` naming a bundled model, that model's folder (the name
    wins over a folder of that name in the working directory, as in ``mfgnet register --model``), else a folder."""
    if isinstance(model, Path):
        if not model.is_dir():  # not a damaged model: a mistyped path
            raise ValueError(f"model {str(model)!r}: no such folder")
        return model
    bundled = bundled_models_dir()
    if model and (bundled / model).is_dir():  # "" would name the folder of bundled models
        return bundled / model
    if model and Path(model).is_dir():  # "" would name the working directory
        return Path(model)
    names = sorted(d.name for d in bundled.iterdir() if d.is_dir() and not d.name.startswith(("_", ".")))
    raise ValueError(f"model {model!r}: no bundled model of that name (bundled: {', '.join(names) or 'none'}) "
                     "and no folder")


def checked_threads(threads: int | None) -> int | None:
    """``threads`` where it is ``None`` or a whole number in ``THREAD_RANGE``, else ``ValueError`` naming it (ONNX
    Runtime took 300 and started 1,500 threads, took -1, and answered 2.5 with a binding's ``TypeError``)."""
    low, high = THREAD_RANGE
    if threads is None:
        return None
    if isinstance(threads, bool) or not isinstance(threads, numbers.Integral) or not low <= threads <= high:
        raise ValueError(f"threads must be a whole number in {low}..{high} (as mfgnet register --threads), "
                         f"got {threads!r}")
    return int(threads)


def read_cloud(cloud: Cloud) -> ArrayLike:
    """``cloud`` itself, or the float64 ``[N, 3]`` points of the file it names."""
    if isinstance(cloud, (str, os.PathLike)):
        from service.pointcloud_io import read_points  # the format readers load only when a file comes

        return read_points(cloud)
    return cloud
