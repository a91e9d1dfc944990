"""``python -m bench.server_memory``: a real server's memory through default requests (DEPLOYMENT's current figures)."""

from __future__ import annotations

import argparse
import json
import zipfile

import e57
import numpy as np
import pytest

from bench.server_memory import ALIGNED_FORMATS, aligned_file, formats_list, main
from model.data import data_dir
from service.formats.moved import source_format
from service.formats.read import read_cloud
from service.manifest import bundled_models_dir

needs_model = pytest.mark.skipif(not (bundled_models_dir() / "general").is_dir(), reason="no bundled 'general' model")
needs_data = pytest.mark.skipif(not data_dir().is_dir(), reason="ModelNet40 absent (set MFGNET_DATA)")


@pytest.mark.parametrize("fmt", ["ply", "pcd", "las", "laz", "e57", "npy", "npz"])
def test_each_aligned_file_reads_as_its_format_with_every_point(tmp_path, fmt) -> None:
    assert fmt in ALIGNED_FORMATS
    path = aligned_file(tmp_path, fmt, 301)
    assert source_format(path) == ("las" if fmt == "laz" else fmt)
    assert read_cloud(path).shape == (301, 3)


def test_aligned_e57_npy_npz_files_hold_what_their_users_keep(tmp_path) -> None:
    assert formats_list("E57, npy,npz,e57") == ["e57", "npy", "npz"]
    xyz = np.random.default_rng(0).random((301, 3)) * 100  # aligned_file's points
    path = aligned_file(tmp_path, "e57", 301)
    assert e57.raw_xml(str(path)).count("<pose ") == 2  # two posed scans of intensity and colour
    scans = e57.read_points(str(path))
    # in the file's frame: scan 0 (the first 151 rows) shifted, scan 1 turned 0.7 rad about z and shifted
    c, s = np.cos(0.7), np.sin(0.7)
    assert np.allclose(scans.points[:151], xyz[:151] + np.array([0, -3, 1.5]), atol=1e-4)
    turned = xyz[151:] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + np.array([10, -3, 1.5])
    assert np.allclose(scans.points[151:], turned, atol=1e-4)
    assert scans.intensity.shape == (301, 1) and scans.color.shape == (301, 3) and scans.color.max() > 0.5
    array = np.load(aligned_file(tmp_path, "npy", 301))
    assert array.dtype == np.float32 and array.shape == (301, 7)  # x, y, z, normals, intensity
    assert np.allclose(np.linalg.norm(array[:, 3:6], axis=1), 1, atol=1e-6)
    path = aligned_file(tmp_path, "npz", 301)
    with np.load(path) as arrays:
        assert {name: (arrays[name].dtype, arrays[name].shape) for name in arrays.files} == {
            "points": (np.float32, (301, 3)),
            "colors": (np.uint8, (301, 3)),
            "labels": (np.int32, (301,)),
        }
    with zipfile.ZipFile(path) as archive:
        assert {member.compress_type for member in archive.infolist()} == {zipfile.ZIP_DEFLATED}


def test_a_format_the_bench_does_not_make_is_refused(tmp_path) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match="xyz"):
        formats_list("ply,xyz")
    with pytest.raises(ValueError, match="'xyz'"):  # not a LAS file named cloud.xyz
        aligned_file(tmp_path, "xyz", 3)
    assert not list(tmp_path.iterdir())


@needs_model
@needs_data
def test_one_model_server_reports_its_memory_at_each_phase(tmp_path) -> None:
    out = tmp_path / "server_memory.json"
    main(["--models", "general", "--small", "2", "--big-points", "5000", "--json", str(out)])
    report = json.loads(out.read_text())
    assert report["models"] == ["general"] and report["small_requests"] == 2 and report["big_points"] == 5000
    rss = report["rss_mib"]
    assert 50 < rss["after_start"] < 1024  # a loaded model, not an empty interpreter nor a runaway
    assert max(rss["after_start"], rss["after_small"], rss["after_big"]) <= rss["peak"]


@pytest.mark.slow  # a benchmark's whole run: on demand (make test-all; decisions/0098)
@needs_model  # the aligned downloads' files are made here, no data set needed
def test_aligned_downloads_report_each_server_peak(tmp_path) -> None:
    out = tmp_path / "aligned.json"
    options = ["--models", "general", "--aligned", "ply,e57", "--aligned-pair", "laz", "--aligned-points", "3000"]
    main([*options, "--json", str(out)])
    report = json.loads(out.read_text())
    assert report["points"] == 3000 and list(report["formats"]) == ["ply", "e57"]
    assert report["pair"]["format"] == "laz"
    for run in (*report["formats"].values(), report["pair"]):
        assert run["answer_mib"] > 0  # the moved file came back
        rss = run["rss_mib"]
        assert 50 < rss["after_start"] <= rss["peak"] and rss["after"] <= rss["peak"]
    pair = report["pair"]
    assert (pair["at_once"], pair["threads"], pair["max_concurrency"]) == (2, 1, 2)  # the manifest's settings
