"""The alternating-pass bench against FPFH + RANSAC + ICP: report shape and the rotation-search option."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import asymmetric_blob

from bench.vs_fpfh import run
from service.manifest import bundled_models_dir


@pytest.mark.skipif(not (bundled_models_dir() / "general" / "manifest.json").exists(), reason="no bundled 'general'")
def test_bench_times_both_methods_per_round_and_records_the_search_mode(tmp_path) -> None:
    pytest.importorskip("open3d", reason="the FPFH baseline needs the bench extra (open3d-cpu)")
    cloud = asymmetric_blob(600, 1)
    R = Rotation.from_euler("zyx", [150, 20, -40], degrees=True).as_matrix()[None].repeat(2, 0)  # [2, 3, 3]
    t = np.array([[0.1, 0.0, -0.2], [0.0, 0.3, 0.1]])
    target = cloud[None] @ R.transpose(0, 2, 1) + t[:, None]  # [2, 600, 3]
    path = tmp_path / "pairs.npz"
    np.savez(path, source=np.repeat(cloud[None], 2, 0).astype(np.float32), target=target.astype(np.float32),
             rotation=R.astype(np.float32), translation=t.astype(np.float32))
    report = run(path, count=2, rounds=2, refine="icp-plane", model="general", rotation_search="on")
    assert report["rotation_search"] == "on" and report["n"] == 2
    for name in ("mfgnet", "fpfh_ransac_icp"):
        assert len(report["methods"][name]["pass_ms_per_pair"]) == 2
    assert len(report["fpfh_over_mfgnet"]["per_round"]) == 2
    assert report["methods"]["mfgnet"]["recall_r5_t005"] == 1.0  # 150 deg: only the search finds it
