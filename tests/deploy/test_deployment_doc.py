"""``docs/DEPLOYMENT.md`` tells an operator what the service really reads and exports.

Every ``MFGNET_*`` variable that the Dockerfile, the manifests or the guide name is a field of ``Settings`` (the
settings ignore unknown names, so a misspelt variable would change nothing, silently); every field has a row in the
guide's settings table with the field's default; every Prometheus metric the app registers is in its metrics table.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

config = pytest.importorskip("service.core.config")

ROOT = Path(__file__).resolve().parents[2]
GUIDE = ROOT / "docs" / "DEPLOYMENT.md"
NAMING_FILES = [ROOT / "Dockerfile", *sorted((ROOT / "deploy").rglob("*.yaml")), GUIDE]
PLACEHOLDERS = {"MFGNET_FOO"}  # the guide's "field `foo` is read from `MFGNET_FOO`"
MiB = 1024 * 1024


def section(title: str) -> str:
    """The guide's text from the ``## title`` heading to the next ``## `` heading."""
    text = GUIDE.read_text()
    start = text.index(f"\n## {title}")
    end = text.find("\n## ", start + 1)
    return text[start:end if end >= 0 else None]


def settings_rows() -> dict[str, str]:
    """``MFGNET_X`` -> its default cell, from the guide's settings table."""
    rows = re.findall(r"^\| `(MFGNET_[A-Z0-9_]+)` \| ([^|]*) \|", section("Settings"), flags=re.MULTILINE)
    return dict(rows)


def documented_default(cell: str) -> object:
    """A default cell as a value: the first backticked word, ``N MiB``, ``empty`` (a list) or ``unset`` (None)."""
    cell = cell.strip()
    if match := re.match(r"`([^`]*)`", cell):
        return match.group(1)
    if match := re.match(r"(\d+) MiB\b", cell):
        return str(int(match.group(1)) * MiB)
    return {"empty": [], "unset": None}[cell.split()[0]]


def field_name(variable: str) -> str:
    return variable.removeprefix("MFGNET_").lower()


@pytest.mark.parametrize("path", NAMING_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_variable_named_is_a_setting(path):
    fields = set(config.Settings.model_fields)
    named = set(re.findall(r"\bMFGNET_[A-Z0-9_]*[A-Z0-9]", path.read_text())) - PLACEHOLDERS
    unknown = sorted(name for name in named if field_name(name) not in fields)
    assert not unknown, f"{path.name} names variables the service does not read: {unknown}"


def test_every_setting_has_a_row_in_the_settings_table():
    documented = {field_name(variable) for variable in settings_rows()}
    missing = sorted(set(config.Settings.model_fields) - documented)
    assert not missing, f"settings without a row in DEPLOYMENT.md's table: {missing}"


@pytest.mark.parametrize("variable", sorted(settings_rows()))
def test_documented_default_is_the_settings_default(variable):
    field = config.Settings.model_fields[field_name(variable)]
    actual = field.get_default(call_default_factory=True)
    documented = documented_default(settings_rows()[variable])
    if documented is None or isinstance(documented, list):
        assert actual == documented, variable
    elif isinstance(actual, bool):
        assert documented == str(actual).lower(), variable
    elif isinstance(actual, (int, float)):
        assert float(documented) == actual, variable
    else:
        assert documented == actual, variable


def test_every_metric_the_app_exports_is_in_the_metrics_table():
    from service.api.metrics import Metrics

    exported = {family.name + ("_total" if family.type == "counter" else "")
                for family in Metrics().registry.collect()}
    table = set(re.findall(r"`(mfgnet_[a-z_]+)`", section("Metrics")))
    assert exported - table == set(), f"exported but not in DEPLOYMENT.md's metrics table: {sorted(exported - table)}"
    assert table - exported == set(), f"in the metrics table but not exported: {sorted(table - exported)}"
