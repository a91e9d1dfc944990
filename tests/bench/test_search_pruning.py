"""`python -m bench.search_pruning`: every pruning variant on every pair, with where and from what it was run."""

from __future__ import annotations

import json

import numpy as np
from provenance_check import assert_made_by_this_checkout
from scipy.spatial.transform import Rotation
from shapes import asymmetric_blob

import service.rotation_search as search_module
from bench.search_pruning import VARIANTS, main


def test_each_variant_searches_each_pair_and_the_report_says_where_and_from_what(tmp_path) -> None:
    source = asymmetric_blob(768, seed=0).astype(np.float32)  # [N, 3]: no turn maps it onto itself
    rotation = Rotation.from_euler("zyx", [150, -40, 70], degrees=True).as_matrix().astype(np.float32)  # src_to_tgt
    translation = np.array([0.1, -0.05, 0.02], np.float32)
    target = asymmetric_blob(768, seed=1).astype(np.float32) @ rotation.T + translation  # another sampling
    pairs = tmp_path / "pairs.npz"
    np.savez(pairs, source=source[None], target=target[None], rotation=rotation[None], translation=translation[None])
    out = tmp_path / "pruning.json"
    defaults = search_module.SEARCH_PRUNE_ITERATIONS, search_module.SEARCH_KEEP
    main(["--pairs", str(pairs), "--json", str(out)])
    assert defaults == (search_module.SEARCH_PRUNE_ITERATIONS, search_module.SEARCH_KEEP)  # put back after the run
    report = json.loads(out.read_text())
    rows = report["files"][str(pairs)]
    assert set(rows) == set(VARIANTS) and all(row["n"] == 1 for row in rows.values())
    assert rows["full"]["right"] == rows["p1k8"]["right"] == [True]  # 150 deg off: the plain pass is not
    assert all(row["search_ms_median"] > 0 and row["recall_r5_t005"] == np.mean(row["right"]) for row in rows.values())
    assert report["machine"]["cpus"] > 0 and report["machine"]["threads"] >= 1
    assert_made_by_this_checkout(report["provenance"])
