"""What ``README.md`` and ``docs/*.md`` tell a user about options, settings, limits and formats is what the code does.

Each check reads the claim from the doc and the value from the code, so that a default, a range, a variable name or a
format that changes on one side fails here instead of drifting: README's options table against the request schema
(``RegisterRequest``), ``mfgnet register``'s flags and the service's defaults; DESIGN's options table against
``RegistrationOptions``; every ``MFGNET_*`` variable the docs name against ``Settings``; values quoted beside a
setting against its default; the file formats against the readers; the runtime's use of scipy against DEPLOYMENT's
licence note. (``tests/deploy/test_deployment_doc.py`` checks DEPLOYMENT's settings and metrics tables;
``test_doc_commands.py`` the commands the docs show.)
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

schemas = pytest.importorskip("service.api.schemas")  # the serve extra

from service.checks import MIN_POINTS, ORTHONORMAL_TOLERANCE  # noqa: E402
from service.core.config import Settings  # noqa: E402
from service.manifest import bundled_models_dir, load_manifest  # noqa: E402
from service.options import DEFAULT_WORKING_SIZE, RegistrationOptions  # noqa: E402
from service.pointcloud_io import READ_SUFFIXES  # noqa: E402
from service.refine_modes import SERVICE_DEFAULT_REFINE  # noqa: E402
from service.request_defaults import DEFAULT_MODEL  # noqa: E402
from service.search_mode import SERVICE_DEFAULT_ROTATION_SEARCH  # noqa: E402
from service.stages.normalise import ICP_DISTANCE  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
DOCS = [README, *sorted((ROOT / "docs").glob("*.md"))]  # not docs/decisions/: historical records
NOT_SETTINGS = {"MFGNET_DATA", "MFGNET_REAL_DATA"}  # data folders of the tests and benchmarks, not the server's
REQUEST_OPTIONS = set(schemas.RegisterRequest.model_fields) - {"source", "target"}


def table(path: Path, heading: str, header: str = "option") -> list[list[str]]:
    """The body rows (cells stripped) of the table under the heading ``## heading...`` of ``path`` whose first header
    cell starts with ``header``."""
    section = path.read_text().split(f"\n## {heading}", 1)[1].split("\n## ", 1)[0]
    for block in re.findall(r"(?:^\|.*\n)+", section, flags=re.M):
        rows = [[cell.strip() for cell in re.split(r"(?<!\\)\|", line)[1:-1]] for line in block.splitlines()]
        if rows[0][0].startswith(header):
            return rows[2:]
    raise AssertionError(f"{path.name}, {heading!r}: no table whose first column is {header!r}")


def names(cell: str) -> list[str]:
    return re.findall(r"`([^`]+)`", cell)


README_OPTIONS = {name: row for row in table(README, "Options") for name in names(row[0]) if not name.startswith("-")}


def schema_of(option: str) -> dict:
    """The JSON schema of a request option, its ``null`` alternative left out."""
    prop = schemas.RegisterRequest.model_json_schema()["properties"][option]
    return next((alt for alt in prop.get("anyOf", []) if alt.get("type") != "null"), prop) | {
        "default": prop.get("default")}


def test_readme_options_table_has_every_request_option_and_no_other():
    assert set(README_OPTIONS) == REQUEST_OPTIONS


def test_readme_options_table_names_flags_that_mfgnet_register_has():
    import typer

    from service.cli import app

    command = typer.main.get_command(app).commands["register"]
    flags = {opt for param in command.params for opt in [*param.opts, *param.secondary_opts]}
    named = {name for row in table(README, "Options") for name in names(row[0]) if name.startswith("-")}
    assert named and named <= flags, sorted(named - flags)


@pytest.mark.parametrize("option", sorted(REQUEST_OPTIONS))
def test_readme_ranges_are_the_schemas(option):
    """``(16-512)`` beside an option is the schema's minimum and maximum, and an option with bounds states them."""
    stated = re.findall(r"\((\d+)-(\d+)\)", " ".join(README_OPTIONS[option][1:3]))
    schema = schema_of(option)
    bounds = [(str(schema["minimum"]), str(schema["maximum"]))] if "minimum" in schema else []
    assert stated == bounds, (option, stated, bounds)


def general_config() -> dict:
    directory = bundled_models_dir() / DEFAULT_MODEL
    if not (directory / "manifest.json").exists():
        pytest.skip(f"bundled model {DEFAULT_MODEL!r} absent")
    return load_manifest(directory).config


def test_readme_defaults_are_the_services():
    default = {name: README_OPTIONS[name][1] for name in README_OPTIONS}
    first = {name: (names(cell) or [cell.split()[0]])[0] for name, cell in default.items()}
    assert first["refine"] == SERVICE_DEFAULT_REFINE
    assert first["rotation_search"] == SERVICE_DEFAULT_ROTATION_SEARCH
    assert first["model"] == DEFAULT_MODEL
    assert first["drop_isolated"] == str(schema_of("drop_isolated")["default"]).lower()
    flags = re.findall(r"`(true|false)`", default["return_correspondences"])
    assert flags == [str(schema_of(o)["default"]).lower() for o in ("return_correspondences", "return_iterations")]
    assert f"the {DEFAULT_WORKING_SIZE} working points" in default["refine_points"]
    config = general_config()
    assert first["keypoints"] == str(config["keypoints"]) and first["iterations"] == str(config["iterations"])
    assert f"within {ORTHONORMAL_TOLERANCE:g} of orthonormal" in README_OPTIONS["initial_transform"][2]


def test_design_options_table_matches_registration_options():
    rows = {names(row[0])[0] if len(names(row[0])) == 1 else tuple(names(row[0])): row
            for row in table(ROOT / "docs" / "DESIGN.md", "Runtime pipeline")}
    library = RegistrationOptions.names() | {"model"}
    for key, row in rows.items():
        for name in key if isinstance(key, tuple) else (key,):
            assert name in library, name
            assert (name in REQUEST_OPTIONS) == ("library only" not in row[0]), name
    defaults = {f: getattr(RegistrationOptions(), f) for f in RegistrationOptions.names()}
    assert rows["working_size"][1] == str(defaults["working_size"])
    config = general_config()
    assert f"({config['keypoints']}, {config['iterations']})" in rows[("keypoints", "iterations")][1]
    assert rows[("icp_max_distance", "icp_max_iterations")][1] == (
        f"{ICP_DISTANCE} normalised units, {defaults['icp_max_iterations']}")
    low, high = schema_of("refine_points")["minimum"], schema_of("refine_points")["maximum"]
    assert f"({low}-{high})" in rows["refine_points"][2]


def named_variables() -> list[tuple[str, str]]:
    return sorted({(path.name, name) for path in DOCS
                   for name in re.findall(r"\bMFGNET_[A-Z0-9_]*[A-Z0-9]\b", path.read_text())} - {
        ("DEPLOYMENT.md", "MFGNET_FOO")})  # its "field `foo` is read from `MFGNET_FOO`"


@pytest.mark.parametrize(("doc", "variable"), named_variables())
def test_every_variable_the_docs_name_is_read(doc, variable):
    if variable in NOT_SETTINGS:
        readers = [p for p in (ROOT / "tests").rglob("*.py") if variable in p.read_text()]
        assert readers, f"{doc} names {variable}, which nothing reads"
    else:
        assert variable.removeprefix("MFGNET_").lower() in Settings.model_fields, f"{doc}: {variable} is no setting"


def setting_default(field: str) -> float:
    value = Settings.model_fields[field].get_default(call_default_factory=True)
    return float(value)


UNITS = {"": 1, "MiB": 2**20, "KiB/s": 2**10, "s": 1}
QUOTED = re.compile(r"`(?:MFGNET_)?([A-Za-z_]+)` (?:\(default )?(\d[\d,]*(?:\.\d+)?)(?: (MiB|KiB/s|s)\b)?")


def quoted_values() -> list[tuple[str, str, str, float]]:
    """(doc, setting, text, value) of every ``\\`max_points\\` 200,000`` or ``\\`MFGNET_TIMEOUT_S\\` (default 30)`` in a
    sentence or table cell that speaks of defaults (not the test servers' own limits, ``\\`limited\\` server``)."""
    found = []
    for path in DOCS:
        text = re.sub(r"\s+", " ", path.read_text())
        for segment in re.split(r"\||(?<=[a-z)]\.) ", text):
            if "default" not in segment or "`limited`" in segment:
                continue
            for field, number, unit in QUOTED.findall(segment):
                field, number = field.lower(), number.rstrip(",")
                if field in Settings.model_fields:
                    found.append((path.name, field, f"{number} {unit}".strip(),
                                  float(number.replace(",", "")) * UNITS[unit or ""]))
    return found


def test_the_docs_quote_setting_values():
    assert len(quoted_values()) >= 10, "the pattern finds few quoted settings: it is wrong"


@pytest.mark.parametrize(("doc", "field", "text", "value"), quoted_values())
def test_quoted_setting_values_are_the_defaults(doc, field, text, value):
    assert value == setting_default(field), f"{doc}: `{field}` {text}, the default is {setting_default(field)}"


def test_readme_limits_are_the_defaults():
    text = re.sub(r"\s+", " ", README.read_text())
    assert f"clouds are `[N, 3]` lists, N >= {MIN_POINTS}" in text
    for number, variable in re.findall(r"([\d,]+) (?:points per cloud )?\(`(MFGNET_\w+)`\)", text):
        assert float(number.replace(",", "")) == setting_default(variable[7:].lower()), (number, variable)
    batch = re.search(r"at most `MFGNET_MAX_BATCH` pairs, (\d+)", text)
    assert batch and float(batch.group(1)) == setting_default("max_batch")


def test_readme_lists_the_formats_the_readers_take():
    listed = re.search(r"^Clouds: `([^`]+)`", README.read_text(), flags=re.M)
    assert listed and sorted(listed.group(1).split()) == sorted(READ_SUFFIXES)


def scipy_modules() -> set[str]:
    """The scipy modules ``service/`` imports (``scipy.fft``, ``scipy.spatial.transform``)."""
    found = set()
    for path in (ROOT / "service").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "scipy":
                found |= {f"{node.module}.{alias.name}" for alias in node.names}
            elif isinstance(node, ast.Import):
                found |= {alias.name for alias in node.names if alias.name.split(".")[0] == "scipy"}
    return found


def test_deployment_names_every_use_of_scipy():
    sentence = re.search(r"The runtime uses scipy only for ([^.]+(?:\.[a-z][^.]*)*)\.",
                         re.sub(r"\s+", " ", (ROOT / "docs" / "DEPLOYMENT.md").read_text()))
    assert sentence, "DEPLOYMENT.md no longer says what the runtime uses scipy for"
    named = set(re.findall(r"`([\w.]+)`", sentence.group(1)))
    used = scipy_modules()
    assert used, "service/ imports no scipy module: the pattern is wrong"
    missing = sorted(m for m in used if not any(m == n or m.endswith("." + n) or m.startswith(n + ".") for n in named))
    assert not missing, f"service/ uses {missing}, which DEPLOYMENT.md's licence note does not name"


MULTISTART_COST = re.compile(r"(\d[\d.]*(?:-\d[\d.]*)?x) the refinement time")


def test_the_multistart_cost_is_stated_alike_in_docs_help_and_schema():
    """``icp-plane-multistart``'s cost, as DESIGN's refinement table states it (with its command), is what
    DEPLOYMENT, README's options table, ``mfgnet register --help`` and the request schema (``/docs``) say."""
    from service.cli.options import RefineOpt

    design = {row[0]: row[1] for row in table(ROOT / "docs" / "DESIGN.md", "Refinement", "`refine`")}
    stated = MULTISTART_COST.findall(design["`icp-plane-multistart`"])
    assert len(stated) == 1, design["`icp-plane-multistart`"]
    settings = {row[0]: row[2] for row in table(ROOT / "docs" / "DEPLOYMENT.md", "Settings", "variable")}
    deployment = settings["`MFGNET_DEFAULT_REFINE`"]
    readme = next(line for line in README.read_text().splitlines() if line.startswith("| `refine` / `--refine`"))
    texts = {"DEPLOYMENT.md": deployment, "README.md options table": readme,
             "mfgnet register --refine": RefineOpt.__metadata__[0].help,
             "RegisterRequest.refine": schemas.REFINE_DESCRIPTION}
    for where, text in texts.items():
        assert MULTISTART_COST.findall(text) == stated, f"{where}: {text}"


def paragraph(path: Path, start: str) -> str:
    """The paragraph of ``path`` that begins with ``start``, its lines joined."""
    text = path.read_text()
    return " ".join(text[text.index(start):].split("\n\n", 1)[0].split())


def test_readme_names_every_field_of_the_response():
    named = set(names(paragraph(README, "The response holds")))
    for model in (schemas.RegisterResponse, schemas.Quality, schemas.Correspondence):
        assert set(model.model_fields) <= named, (model.__name__, sorted(set(model.model_fields) - named))


def test_design_names_the_fields_of_the_pages_view_response():
    from service.api.routes.page import ViewResponse

    text = paragraph(ROOT / "docs" / "DESIGN.md", "- **The page**")
    view = re.search(r"`POST /v1/register/view` returns (.*?) \(at most", text)
    assert view and set(names(view.group(1))) - {"/v1/register"} == set(ViewResponse.model_fields), view


def test_reliability_states_the_json_body_counts():
    from service.api.bodies import EXTRA_JSON_VALUES, MAX_JSON_STRINGS, MAX_JSON_TEXT_BYTES, VALUES_PER_POINT

    text = paragraph(ROOT / "docs" / "RELIABILITY.md", "- **Limits**")
    words = {4: "four"}
    assert (f"({words[VALUES_PER_POINT]} per point of 2 x `max_points`, and {EXTRA_JSON_VALUES:,} more)" in text)
    assert f"against {MAX_JSON_STRINGS:,} strings and {MAX_JSON_TEXT_BYTES // 1024} KiB of text" in text


FACTOR = r"(\d[\d.]*(?:-\d[\d.]*)?)x"
SEARCH_COST = re.compile(FACTOR + r" the time with a refinement, " + FACTOR + " without")
SEARCH_COST_RUNS = ("search_cost_dense170.json", "search_cost_dense180_s21.json", "search_cost_real_scans.json")


def _states_the_range_of(stated: str, ratios: list[float]) -> bool:
    """``stated`` ("1.5-2.6" or "12") is the lowest and highest of ``ratios`` at its own number of decimals."""
    low, _, high = stated.partition("-")
    high = high or low

    def rounded(value: float, like: str) -> float:
        return round(value, len(like.partition(".")[2]))

    return rounded(min(ratios), low) == float(low) and rounded(max(ratios), high) == float(high)


def test_the_rotation_search_cost_is_stated_alike_in_docs_help_and_schema():
    """The rotation search's cost (forced on against off, with a refinement and without), as ROTATION_SEARCH.md
    states it beside its command, is the range of the stored runs' ratios and what ``mfgnet register
    --rotation-search --help`` and the request schema (``/docs``) say."""
    import json

    from service.cli.options import RotationSearchOpt

    doc = " ".join((ROOT / "docs" / "ROTATION_SEARCH.md").read_text().split())
    stated = SEARCH_COST.findall(doc)
    assert len(stated) == 1, stated
    assert "python -m bench.settings --scans" in doc and "search_cost_$f.json" in doc  # the command beside it
    refined, plain = [], []  # per stored run: time with the search on over off (medians per pair)
    for name in SEARCH_COST_RUNS:
        rows = json.loads((ROOT / "results" / "general-0.2.0" / name).read_text())["settings"]
        ms = {(row["options"]["refine"], row["options"]["rotation_search"]): row["ms_per_pair_median"] for row in rows}
        refined.append(ms["icp-plane", True] / ms["icp-plane", False])
        plain.append(ms["none", True] / ms["none", False])
    with_refinement, without = stated[0]
    assert _states_the_range_of(with_refinement, refined), (with_refinement, refined)
    assert _states_the_range_of(without, plain), (without, plain)
    texts = {"mfgnet register --rotation-search": RotationSearchOpt.__metadata__[0].help,
             "RegisterRequest.rotation_search": schemas.ROTATION_SEARCH_DESCRIPTION}
    for where, text in texts.items():
        assert SEARCH_COST.findall(" ".join(text.split())) == stated, f"{where}: {text}"
