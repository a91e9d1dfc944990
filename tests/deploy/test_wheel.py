"""The wheel a user gets from ``pip install`` (not the checkout), and the sdist: what they hold and declare.

The wheel is built from a copy of the packages, ``pyproject.toml``, ``PACKAGE.md`` and ``LICENSE`` with the dev
venv's setuptools (no index needed, a few seconds). The sdist is built with ``python -m build`` from a copy of the
checkout (checkpoints, results and runs included), and a wheel from that sdist, as a release builds them.
``tests/deploy/test_runtime_image.py`` installs the container's wheel and serves from it; these checks are the cheap
ones on the plain builds.
"""

from __future__ import annotations

import ast
import hashlib
import json
import re
import shutil
import subprocess
import sys
import tarfile
import tomllib
import zipfile
from email.parser import HeaderParser
from functools import cache
from importlib.metadata import PackageNotFoundError, distribution, packages_distributions
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.specifiers import SpecifierSet
from packaging.utils import canonicalize_name
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("service", "model", "export", "bench")
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
PROJECT = PYPROJECT["project"]
# Which dependency groups a package's modules may import from (the extras that install them).
GROUPS_OF = {
    "service": ("formats", "serve"),
    "model": ("formats", "serve", "train"),
    "export": ("formats", "serve", "train"),
    "bench": ("formats", "serve", "train", "bench"),
}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> zipfile.ZipFile:
    """``pip wheel --no-deps`` of a copy of the project's packaged files."""
    work = tmp_path_factory.mktemp("wheel")
    source = work / "source"
    for name in ("pyproject.toml", "PACKAGE.md", "LICENSE"):
        (source / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, source / name)
    for package in PACKAGES:
        shutil.copytree(ROOT / package, source / package, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    built = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "--no-cache-dir",
            "--disable-pip-version-check",
            "-w",
            str(work / "dist"),
            str(source),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert built.returncode == 0, built.stdout[-3000:] + built.stderr[-3000:]
    (path,) = (work / "dist").glob("mfgnet-*.whl")
    with zipfile.ZipFile(path) as archive:
        yield archive


def metadata(wheel: zipfile.ZipFile):
    (name,) = [n for n in wheel.namelist() if re.fullmatch(r"mfgnet-[^/]+\.dist-info/METADATA", n)]
    return HeaderParser().parsestr(wheel.read(name).decode())


def test_wheel_holds_only_code_bundled_models_and_the_page(wheel):
    """Python sources, service/models/<name>/ (ONNX graphs + manifest), service/web, metadata: no checkpoints,
    tests, results, runs, data or caches."""
    names = [n for n in wheel.namelist() if not n.endswith("/")]
    allowed = re.compile(
        r"(service|model|export|bench)/.+\.py|service/models/[^/]+/([^/]+\.onnx|manifest\.json)"
        r"|service/web/[^/]+\.(html|js|css)|mfgnet-[^/]+\.dist-info/.+"
    )
    unexpected = [n for n in names if not allowed.fullmatch(n)]
    assert not unexpected, f"not code, a bundled model or the page: {unexpected[:10]}"
    assert not [n for n in names if re.search(r"(^|/)(tests?|results|runs|data|checkpoints)/", n)]
    shipped = {p.relative_to(ROOT).as_posix() for p in (ROOT / "service" / "web").iterdir() if p.is_file()}
    assert shipped <= set(names), shipped - set(names)


def test_wheel_bundles_every_model_with_graphs_matching_its_manifest(wheel):
    bundled = sorted(p.parent.name for p in (ROOT / "service" / "models").glob("*/manifest.json"))
    assert bundled
    for model in bundled:
        manifest = json.loads(wheel.read(f"service/models/{model}/manifest.json"))
        for role, graph in manifest["graphs"].items():
            data = wheel.read(f"service/models/{model}/{graph['file']}")
            assert hashlib.sha256(data).hexdigest() == graph["sha256"], f"{model} {role}"


def test_wheel_metadata_names_the_licence_readme_and_entry_point(wheel):
    meta = metadata(wheel)
    assert meta["License-Expression"] == "MIT" and meta.get_all("License-File") == ["LICENSE"]
    assert meta["Description-Content-Type"] == "text/markdown"
    assert meta.get_payload().strip() == (ROOT / "PACKAGE.md").read_text().strip()
    (entry_points,) = [n for n in wheel.namelist() if n.endswith(".dist-info/entry_points.txt")]
    assert "mfgnet = service.cli:main" in wheel.read(entry_points).decode()


# Extras the suite's environment may lack (`make test` installs train and dev; the Open3D tests skip without bench):
# their pins are checked where they are installed.
OPTIONAL_EXTRAS = ("bench",)


def pinned() -> dict[str, Requirement]:
    """Every ``name==version`` requirement of the base and of each extra, by canonical name."""
    extras = PROJECT["optional-dependencies"].values()
    requirements = [*PROJECT["dependencies"], *(r for extra in extras for r in extra)]
    return {canonicalize_name(r.name): r for r in map(Requirement, requirements) if r.name != "mfgnet"}


def optional() -> set[str]:
    """Canonical names pinned only by :data:`OPTIONAL_EXTRAS`."""
    extras = PROJECT["optional-dependencies"]
    others = {
        canonicalize_name(Requirement(r).name)
        for group, rs in extras.items()
        if group not in OPTIONAL_EXTRAS
        for r in rs
    } | {canonicalize_name(Requirement(r).name) for r in PROJECT["dependencies"]}
    return {canonicalize_name(Requirement(r).name) for group in OPTIONAL_EXTRAS for r in extras[group]} - others


def installed(name: str) -> bool:
    try:
        distribution(name)
    except (PackageNotFoundError, StopIteration):  # Python 3.11's from_name can leak the StopIteration
        return False
    return True


def test_every_dependency_is_pinned_to_the_tested_version():
    """The pins are the dev venv's versions (the ones the suite runs on; a local label such as +cpu aside)."""
    for name, requirement in pinned().items():
        (spec,) = requirement.specifier
        assert spec.operator == "==", requirement
        if not installed(name):
            assert name in optional(), f"{name} is declared but not installed in the test environment"
            continue
        tested = Version(distribution(name).version)
        assert Version(tested.public) == Version(spec.version), f"{name}: pinned {spec.version}, tested {tested}"


def test_requires_python_admits_no_version_a_pinned_dependency_refuses():
    """The oldest Python that ``requires-python`` admits can install every pinned version."""
    requires_python = SpecifierSet(PROJECT["requires-python"])
    oldest = next(v for v in (Version(f"3.{minor}") for minor in range(8, 20)) if v in requires_python)
    refused = {}
    for name in pinned():
        if not installed(name) and name in optional():
            continue
        theirs = distribution(name).metadata["Requires-Python"]
        if theirs and oldest not in SpecifierSet(theirs):
            refused[name] = theirs
    assert not refused, f"requires-python {requires_python} admits {oldest}, which these pins refuse: {refused}"


def module_imports(path: Path, *, module_level_only: bool) -> set[str]:
    """Top-level names of the absolute imports in a file (module level only: not in functions or TYPE_CHECKING)."""

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if module_level_only and isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            if module_level_only and isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                continue
            if isinstance(child, ast.Import):
                found.update(alias.name.split(".")[0] for alias in child.names)
            elif isinstance(child, ast.ImportFrom) and child.level == 0 and child.module:
                found.add(child.module.split(".")[0])
            visit(child)

    found: set[str] = set()
    visit(ast.parse(path.read_text()))
    return {name for name in found if name not in sys.stdlib_module_names and name not in PACKAGES}


@cache
def declared(groups: tuple[str, ...]) -> set[str]:
    """Canonical names of the base dependencies and of ``groups``' extras."""
    extras = PROJECT["optional-dependencies"]
    requirements = [*PROJECT["dependencies"], *(r for group in groups for r in extras[group])]
    return {canonicalize_name(Requirement(r).name) for r in requirements}


def undeclared(paths: list[Path], groups: tuple[str, ...], *, module_level_only: bool = False) -> dict[str, list[str]]:
    """``{module: [files]}`` of third-party imports whose distribution is not declared in base + ``groups``."""
    owners = packages_distributions()
    missing: dict[str, list[str]] = {}
    for path in paths:
        for module in module_imports(path, module_level_only=module_level_only):
            # a module of an optional extra that is not installed here: its distribution by name ("open3d-cpu")
            fallback = [d for d in optional() if d == module or d.startswith(module + "-")]
            distributions = {canonicalize_name(d) for d in owners.get(module, fallback or [module])}
            if not distributions & declared(groups):
                missing.setdefault(module, []).append(path.relative_to(ROOT).as_posix())
    return missing


@pytest.mark.parametrize("package", PACKAGES)
def test_every_third_party_import_is_a_declared_dependency(package):
    """Each distribution a package imports is declared (base or an extra that installs that side), not left to
    arrive as another one's dependency."""
    missing = undeclared(sorted((ROOT / package).rglob("*.py")), GROUPS_OF[package])
    assert not missing, f"imported by {package}/ but not declared in pyproject.toml: {missing}"


def test_the_cli_starts_on_the_base_dependencies():
    """``mfgnet`` (help, models, the extras' hints) imports at start only what ``pip install mfgnet`` installs."""
    loaded = subprocess.run(
        [sys.executable, "-c", "import sys, service.cli; print(' '.join(sys.modules))"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert loaded.returncode == 0, loaded.stderr
    modules = [m for m in loaded.stdout.split() if m.split(".")[0] == "service"]
    files = [ROOT / (m.replace(".", "/") + ".py") for m in modules]
    files = [f if f.is_file() else f.with_suffix("") / "__init__.py" for f in files]
    missing = undeclared(files, (), module_level_only=True)
    assert not missing, f"imported when mfgnet starts, not in the base dependencies: {missing}"


def test_readme_names_the_oldest_python_requires_python_admits():
    oldest = re.fullmatch(r">=(3\.\d+)", PROJECT["requires-python"]).group(1)
    assert f"(Python {oldest} or newer)" in (ROOT / "README.md").read_text()


# ------------------------------------------------------------------------------ the sdist and its wheel

# Not copied into the checkout's copy the sdist is built from: the venv, VCS data, browser packages, build outputs.
NOT_COPIED = shutil.ignore_patterns(
    ".git",
    ".venv",
    "node_modules",
    "__pycache__",
    "*.pyc",
    "build",
    "dist",
    "*.egg-info",
    ".pytest_cache",
    ".ruff_cache",
    ".hypothesis",
    ".benchmarks",
)
# Listed in a stale egg-info's SOURCES.txt, which setuptools reads back into a new sdist unless MANIFEST.in prunes them.
STALE_SOURCES = ("model/checkpoints/general.pt", "results/README.md", "runs/stale.log", "tests/conftest.py")
# Bytecode a test run leaves in the checkout (`make test` writes it, decisions/0099): never in the sdist or the wheel.
BYTECODE = ("service/__pycache__/registrar.cpython-311.pyc", "model/__pycache__/train.cpython-311.pyc")


@pytest.fixture(scope="module")
def distributions(tmp_path_factory) -> dict[str, Path]:
    """``python -m build`` of a copy of the checkout: the sdist, then the wheel built from that sdist."""
    work = tmp_path_factory.mktemp("dists")
    source = work / "source"
    shutil.copytree(ROOT, source, ignore=NOT_COPIED)
    for stale in (*STALE_SOURCES, *BYTECODE):
        (source / stale).parent.mkdir(parents=True, exist_ok=True)
        (source / stale).touch()
    (source / "mfgnet.egg-info").mkdir()
    (source / "mfgnet.egg-info" / "SOURCES.txt").write_text("\n".join(STALE_SOURCES) + "\n")
    built = subprocess.run(
        [sys.executable, "-m", "build", "--no-isolation", "--outdir", str(work / "dist"), str(source)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert built.returncode == 0, built.stdout[-3000:] + built.stderr[-3000:]
    (sdist,) = (work / "dist").glob("mfgnet-*.tar.gz")
    (wheel_path,) = (work / "dist").glob("mfgnet-*.whl")
    return {"sdist": sdist, "wheel": wheel_path}


def sdist_names(sdist: Path) -> list[str]:
    """The sdist's files, relative to its top folder (``mfgnet-<version>/``)."""
    with tarfile.open(sdist) as archive:
        return sorted(m.name.split("/", 1)[1] for m in archive.getmembers() if m.isfile())


def test_sdist_holds_what_the_build_needs_and_the_docs_not_checkpoints_or_results(distributions):
    names = sdist_names(distributions["sdist"])
    allowed = re.compile(
        r"(service|model|export|bench)/.+\.py|service/models/[^/]+/([^/]+\.onnx|manifest\.json)"
        r"|service/web/[^/]+\.(html|js|css)|docs/.+\.md|mfgnet\.egg-info/[^/]+"
        r"|pyproject\.toml|setup\.cfg|PKG-INFO|MANIFEST\.in|LICENSE|PACKAGE\.md|README\.md|CHANGELOG\.md"
    )
    unexpected = [n for n in names if not allowed.fullmatch(n)]
    assert not unexpected, f"in the sdist, neither a build input nor documentation: {unexpected[:10]}"
    assert not [n for n in names if re.search(r"(^|/)(tests?|results|runs|checkpoints|\.venv|node_modules)/", n)]
    # the documentation README.md names resolves in the unpacked sdist
    named = set(re.findall(r"\b(docs/[\w./-]+\.md|CHANGELOG\.md|LICENSE)\b", (ROOT / "README.md").read_text()))
    assert named and not named - set(names), sorted(named - set(names))
    assert {p.relative_to(ROOT).as_posix() for p in (ROOT / "docs").rglob("*.md")} <= set(names)


def test_the_wheel_built_from_the_sdist_is_the_direct_wheel(distributions, wheel):
    with zipfile.ZipFile(distributions["wheel"]) as from_sdist:
        assert sorted(from_sdist.namelist()) == sorted(wheel.namelist())
        assert metadata(from_sdist).as_string() == metadata(wheel).as_string()


def test_twine_check_passes_on_the_sdist_and_the_wheel(distributions):
    """The metadata and the description render as the package index renders them (``--strict``: no warnings)."""
    checked = subprocess.run(
        [sys.executable, "-m", "twine", "check", "--strict", str(distributions["sdist"]), str(distributions["wheel"])],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert checked.returncode == 0, checked.stdout[-3000:] + checked.stderr[-3000:]


def test_metadata_carries_authors_keywords_and_index_classifiers(wheel):
    from trove_classifiers import classifiers as known

    meta = metadata(wheel)
    holder = re.search(r"^Copyright \(c\) (.+)$", (ROOT / "LICENSE").read_text(), flags=re.M).group(1).strip()
    assert meta["Author"] == holder
    assert len(meta["Keywords"].split(",")) >= 5
    classifiers = meta.get_all("Classifier") or []
    assert not set(classifiers) - known, f"the package index refuses these: {set(classifiers) - known}"
    oldest = re.fullmatch(r">=(3\.\d+)", PROJECT["requires-python"]).group(1)
    assert {
        "Programming Language :: Python :: 3 :: Only",
        f"Programming Language :: Python :: {oldest}",
        "Operating System :: POSIX :: Linux",
        "Topic :: Scientific/Engineering",
        "Topic :: Scientific/Engineering :: Artificial Intelligence",
        "Topic :: Scientific/Engineering :: Image Recognition",
    } <= set(classifiers), classifiers
    assert not [c for c in classifiers if c.startswith("License ::")]  # License-Expression says it (PEP 639)
    # no address that sends a reader nowhere
    urls = meta.get_all("Project-URL") or []
    assert not [u for u in urls if re.search(r"example\.(com|org)|localhost|127\.0\.0\.1|TODO|XXX", u)], urls


def test_package_description_names_the_extras_and_the_torch_pin():
    text = (ROOT / "PACKAGE.md").read_text()
    extras = set(PROJECT["optional-dependencies"]) - {"dev"}
    named = set(re.findall(r"^Extras: (.+?)\.", text, flags=re.M | re.S)[0].replace("\n", " ").split("`")[1::2])
    assert named == extras, named ^ extras
    (torch,) = [r for r in PROJECT["optional-dependencies"]["train"] if r.startswith("torch==")]
    assert re.findall(r"\btorch==[\w.]+", text) == [torch]
