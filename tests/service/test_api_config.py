"""Specification of ``service.core.config.Settings``: ``MFGNET_*`` variables, defaults, list parsing."""

from __future__ import annotations

import os

import pytest
from pydantic import ValidationError

from service.core.config import Settings


@pytest.fixture(autouse=True)
def clean_env(monkeypatch):
    for key in list(os.environ):
        if key.startswith("MFGNET_"):
            monkeypatch.delenv(key)


def test_defaults_are_safe():
    s = Settings()
    assert s.model_dirs == [] and s.default_model == "general"
    assert (s.host, s.port, s.threads) == ("127.0.0.1", 8080, 2)
    assert (s.max_points, s.max_body_bytes) == (200_000, 64 * 1024 * 1024)
    assert (s.max_concurrency, s.max_queue, s.timeout_s) == (2, 16, 30)
    assert s.api_key is None and s.cors_origins == []


@pytest.mark.parametrize("value", ["/a/models,/b", "/a/models:/b", " /a/models , /b ", '["/a/models", "/b"]'])
def test_model_dirs_are_comma_or_colon_separated(monkeypatch, value):
    monkeypatch.setenv("MFGNET_MODEL_DIRS", value)
    assert Settings().model_dirs == ["/a/models", "/b"]


def test_environment_sets_every_field(monkeypatch):
    monkeypatch.setenv("MFGNET_PORT", "9000")
    monkeypatch.setenv("MFGNET_MAX_QUEUE", "0")
    monkeypatch.setenv("MFGNET_API_KEY", "s3cret")
    monkeypatch.setenv("MFGNET_CORS_ORIGINS", "https://a.example, https://b.example:8443")
    s = Settings()
    assert s.port == 9000 and s.max_queue == 0
    assert s.api_key.get_secret_value() == "s3cret" and "s3cret" not in repr(s)
    assert s.cors_origins == ["https://a.example", "https://b.example:8443"]


def test_cors_origins_are_compared_as_browsers_send_them(monkeypatch):
    """An origin written with a trailing slash or upper case never matched the ``Origin`` header browsers send (lower
    case, no slash): every preflight from it was refused, with nothing said at start."""
    monkeypatch.setenv("MFGNET_CORS_ORIGINS", "https://App.Example.com/ , HTTPS://b.example:8443, *")
    assert Settings().cors_origins == ["https://app.example.com", "https://b.example:8443", "*"]
    for wrong in ("https://a.example/app", "a.example", "https://a.example?x=1", "ftp://a.example"):
        monkeypatch.setenv("MFGNET_CORS_ORIGINS", wrong)
        with pytest.raises(ValueError, match="not an origin: expected scheme://host"):
            Settings()


def test_empty_api_key_means_no_key(monkeypatch):
    monkeypatch.setenv("MFGNET_API_KEY", "  ")
    assert Settings().api_key is None


@pytest.mark.parametrize(
    ("field", "value"), [("port", 70000), ("threads", 0), ("max_concurrency", 0), ("timeout_s", 0)]
)
def test_out_of_range_settings_are_refused(field, value):
    with pytest.raises(ValidationError, match=field):
        Settings(**{field: value})


def test_models_restricts_the_served_models(monkeypatch):
    from service.api.registry import ModelRegistry
    from service.manifest import bundled_models_dir

    if not {"clean", "general"} <= {d.name for d in bundled_models_dir().iterdir()}:
        pytest.skip("needs the bundled clean and general models")
    monkeypatch.setenv("MFGNET_MODELS", "general, clean")
    settings = Settings()
    assert settings.models == ["general", "clean"]
    only = ModelRegistry.discover(settings.model_dirs, only=settings.models)
    assert set(only.entries) == {"general", "clean"}
    assert set(ModelRegistry.discover([], only=["general"]).entries) == {"general"}
    assert {"general", "clean"} < set(ModelRegistry.discover([]).entries)  # default: every bundled model
    with pytest.raises(ValueError, match="not found: nope"):
        ModelRegistry.discover([], only=["general", "nope"])


def test_a_model_folder_of_model_dirs_takes_the_place_of_the_bundled_model_of_its_name(tmp_path):
    """The server kept the bundled ``clean`` and left a re-exported ``clean`` under MFGNET_MODEL_DIRS unserved (with a
    log line), while ``mfgnet register --model-dir`` used the re-exported one."""
    import shutil

    from service.api.registry import ModelRegistry
    from service.manifest import bundled_models_dir

    if not (bundled_models_dir() / "clean").is_dir():
        pytest.skip("needs the bundled clean model")
    shutil.copytree(bundled_models_dir() / "clean", tmp_path / "clean")
    registry = ModelRegistry.discover([str(tmp_path)])
    assert registry.entries["clean"].directory == tmp_path / "clean"
    assert registry.entries["general"].directory.parent == bundled_models_dir()  # the others are still served
    assert registry.duplicates == ["clean"]


def test_the_only_served_model_is_the_default_when_the_configured_one_is_not_served():
    from service.api.app import effective_default_model
    from service.api.registry import ModelRegistry, UnknownModelsError
    from service.manifest import bundled_models_dir

    if not {"clean", "general"} <= {d.name for d in bundled_models_dir().iterdir()}:
        pytest.skip("needs the bundled clean and general models")
    settings = Settings()
    assert effective_default_model(settings, ModelRegistry.discover([], only=["clean"])) == "clean"
    assert effective_default_model(settings, ModelRegistry.discover([], only=["clean", "general"])) == "general"
    explicit = Settings(default_model="unseen")  # several models and the configured one absent: every default 404
    with pytest.raises(UnknownModelsError, match=r"MFGNET_DEFAULT_MODEL is 'unseen', which this server does not "
                                                 r"serve \(it serves clean, general\)"):
        effective_default_model(explicit, ModelRegistry.discover([], only=["clean", "general"]))
