"""bench.search_network: another model's network in the rotation search, beside general, on real cases."""

from __future__ import annotations

import json

import numpy as np
import pytest
from provenance_check import assert_made_by_this_checkout

from bench.real_scans import data_dir, load_cases
from bench.search_network import main
from service.manifest import bundled_models_dir
from service.registrar import default_threads

PAIR = "dragon_96_48"  # its turned image still needs the search (too little overlap for the feature candidate)
needs_data = pytest.mark.skipif(not (data_dir() / f"{PAIR}.npz").exists(),
                                reason=f"real-scan set absent ({data_dir()}; set MFGNET_REAL_DATA)")


@needs_data
def test_general_as_its_own_search_network_changes_nothing(tmp_path):
    out = tmp_path / "report.json"
    report = main([str(bundled_models_dir() / "general"), "--pairs", PAIR, "--seeds", "0", "--turns", "1",
                   "--scales", "1", "--json", str(out)])
    plain, swapped = report["totals"]["general"], report["totals"]["search network"]
    assert plain["cases"] == swapped["cases"] == 2 and report["differ"] == []
    assert {k: v for k, v in plain.items() if k != "seconds"} == {k: v for k, v in swapped.items() if k != "seconds"}
    for a, b in zip(report["rows"]["general"], report["rows"]["search network"], strict=True):
        assert a["rotation_error_deg"] == b["rotation_error_deg"]
    written = json.loads(out.read_text())
    assert written["search_model"].endswith("general")
    assert_made_by_this_checkout(written["provenance"], "general", bundled_models_dir() / "general")  # both roles
    assert written["machine"]["threads"] == default_threads() and written["machine"]["cpus"] > 0


@needs_data
def test_the_search_runs_the_other_registrars_network(monkeypatch):
    import bench.search_network as bench

    runners = bench.registrars([bundled_models_dir() / "general"])
    seen = []
    real_search = bench.search

    def recording(registrar, *args, **kwargs):
        seen.append(registrar)
        return real_search(registrar, *args, **kwargs)

    monkeypatch.setattr(bench, "search", recording)
    case = next(c for c in load_cases(data_dir(), 0, (1.0,), [PAIR], 1) if c.variant == "turned")
    runners["search network"].register(case.source, case.target, refine="icp-plane", rotation_search="auto")
    assert seen and all(r is not runners["search network"] for r in seen)  # searched, with the other registrar
    seen.clear()
    runners["general"].register(case.source, case.target, refine="icp-plane", rotation_search="auto")
    assert not seen  # general's own search stage


def test_a_model_normalised_otherwise_is_refused(tmp_path, capsys):
    cloud = np.zeros((20, 3), np.float32)  # a set of one pair: the models' check refuses before any case loads
    np.savez(tmp_path / "a.npz", source=cloud, target=cloud, transform=np.eye(4), sensor="cyberware-range")
    with pytest.raises(SystemExit) as ended:
        main([str(bundled_models_dir() / "unseen"), "--data", str(tmp_path), "--pairs", "a", "--seeds", "0",
              "--turns", "1"])
    assert ended.value.code == 2 and "reference radius" in capsys.readouterr().err
    from bench.search_network import registrars

    with pytest.raises(ValueError, match="reference radius"):  # called on its own, before any model loads
        registrars([bundled_models_dir() / "unseen"])


@needs_data
def test_derived_cases_are_the_held_out_pairs_once_as_scanned():
    from bench.search_network import cases

    picked = cases(data_dir(), [0, 1], 2, (1.0,), ["dragon_72_0"], derived=True)
    assert [(c.name, c.variant) for c in picked] == [("dragon_72_0", v) for v in ("scanned", "turned", "turned-2",
                                                                                   "turned@seed1", "turned-2@seed1")]
    assert all(c.name not in {p.stem for p in data_dir().glob("*.npz")} for c in picked)


@pytest.mark.slow  # a benchmark's whole run: on demand (make test-all; decisions/0098)
@needs_data
def test_several_candidates_take_turns_beside_one_general(tmp_path):
    import shutil

    candidates = []
    for name in ("first", "second"):  # general's own network under two names: nothing may change
        shutil.copytree(bundled_models_dir() / "general", tmp_path / name)
        manifest = tmp_path / name / "manifest.json"
        manifest.write_text(json.dumps({**json.loads(manifest.read_text()), "name": name}))  # folder = name
        candidates.append(str(tmp_path / name))
    report = main([*candidates, "--pairs", PAIR, "--seeds", "0", "--turns", "1", "--scales", "1"])
    assert list(report["totals"]) == ["general", "first", "second"] and report["differ"] == []
    assert report["search_model"] == candidates
    assert_made_by_this_checkout(report["provenance"], "general", *candidates)  # named "first", "second"
    for rows in zip(*report["rows"].values(), strict=True):
        assert len({row["rotation_error_deg"] for row in rows}) == 1


def test_candidates_need_distinct_names(tmp_path):
    from bench.search_network import variant_names

    assert variant_names([tmp_path / "a"]) == ("general", "search network")
    with pytest.raises(ValueError, match="distinct folder names"):
        variant_names([tmp_path / "x" / "a", tmp_path / "y" / "a"])
