"""Classical registration that users would otherwise pick (Open3D; the ``bench`` extra only).

FPFH + RANSAC + ICP and FGR, with parameters scaled by a voxel size (0.05 for unit-sphere shapes,
the scale of the paper's protocol).
"""

from __future__ import annotations

import argparse
import importlib.util
import time
from collections.abc import Callable

import numpy as np

DEFAULT_VOXEL = 0.05
# In a checkout, after `make install-dev` (docs/BENCHMARKS.md); `pip install 'mfgnet[bench]'` looked for the package on
# an index
OPEN3D_HINT = "classical baselines need Open3D (the bench extra): .venv/bin/pip install -e '.[bench]' in the checkout"


def open3d_missing() -> str | None:
    """:data:`OPEN3D_HINT` where Open3D is not installed, else ``None``: asked before a run, not after its stages."""
    return OPEN3D_HINT if importlib.util.find_spec("open3d") is None else None


def refuse_without_open3d(parser: argparse.ArgumentParser, instead: str | None = "--no-fpfh") -> None:
    """``parser.error`` (exit 2) naming the install, and ``instead`` where given, where Open3D is not installed."""
    if (hint := open3d_missing()) is not None:
        parser.error(hint + (f"; or {instead}" if instead else ""))


def refuse_fpfh_without_open3d(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """:func:`refuse_without_open3d` where the run compares with FPFH + RANSAC + ICP (``args.no_fpfh`` unset). Called
    after the run's other usage checks, before the service's cases (not after them)."""
    if not args.no_fpfh:
        refuse_without_open3d(parser)


def _o3d():
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - depends on the extra
        raise ImportError(OPEN3D_HINT) from exc
    return o3d


def _prepare(points: np.ndarray, voxel: float):
    """Open3D cloud with normals and FPFH features (no down-sampling below ~1k points)."""
    o3d = _o3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if len(points) > 2000:
        pcd = pcd.voxel_down_sample(voxel)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100)
    )
    return pcd, fpfh


def fpfh_ransac_icp(
    src: np.ndarray, tgt: np.ndarray, voxel: float = DEFAULT_VOXEL, icp: bool = True, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """``src_to_tgt`` pose by FPFH features, RANSAC (100k iterations, 0.999) and point-to-point ICP."""
    o3d = _o3d()
    reg = o3d.pipelines.registration
    o3d.utility.random.seed(seed)
    (ps, fs), (pt, ft) = _prepare(src, voxel), _prepare(tgt, voxel)
    distance = 1.5 * voxel
    result = reg.registration_ransac_based_on_feature_matching(
        ps,
        pt,
        fs,
        ft,
        True,
        distance,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(100000, 0.999),
    )
    T = result.transformation
    if icp:
        full_s = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(src, np.float64)))
        full_t = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(tgt, np.float64)))
        T = reg.registration_icp(
            full_s,
            full_t,
            2 * voxel,
            T,
            reg.TransformationEstimationPointToPoint(),
            reg.ICPConvergenceCriteria(max_iteration=30),
        ).transformation
    T = np.asarray(T)
    return T[:3, :3], T[:3, 3]


def fgr(src: np.ndarray, tgt: np.ndarray, voxel: float = DEFAULT_VOXEL) -> tuple[np.ndarray, np.ndarray]:
    """``src_to_tgt`` pose by Fast Global Registration on FPFH features."""
    o3d = _o3d()
    reg = o3d.pipelines.registration
    (ps, fs), (pt, ft) = _prepare(src, voxel), _prepare(tgt, voxel)
    result = reg.registration_fgr_based_on_feature_matching(
        ps, pt, fs, ft, reg.FastGlobalRegistrationOption(maximum_correspondence_distance=0.5 * voxel)
    )
    T = np.asarray(result.transformation)
    return T[:3, :3], T[:3, 3]


def fpfh_ransac(src: np.ndarray, tgt: np.ndarray, voxel: float = DEFAULT_VOXEL) -> tuple[np.ndarray, np.ndarray]:
    """FPFH + RANSAC without the final ICP."""
    return fpfh_ransac_icp(src, tgt, voxel, icp=False)


METHODS = {"fpfh-ransac-icp": fpfh_ransac_icp, "fpfh-ransac": fpfh_ransac, "fgr": fgr}


def run_method(method: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]], pairs: dict[str, np.ndarray],
               progress: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Poses ``[M, 3, 3]``, ``[M, 3]`` of ``method(src, tgt)`` over the pairs and the seconds spent.

    The method first runs once on the first pair, untimed: Open3D's import and set-up (~3 s on the
    development VM) would otherwise be charged to the pairs of whichever method runs first.
    """
    from tqdm import tqdm

    if len(pairs["source"]):
        method(pairs["source"][0], pairs["target"][0])
    Rs, ts = [], []
    begin = time.perf_counter()
    items = zip(pairs["source"], pairs["target"], strict=True)
    for src, tgt in tqdm(items, total=len(pairs["source"]), desc="evaluate", unit="pair", disable=not progress):
        R, t = method(src, tgt)
        Rs.append(R)
        ts.append(t)
    return np.stack(Rs), np.stack(ts), time.perf_counter() - begin
