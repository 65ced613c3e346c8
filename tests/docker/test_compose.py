"""docker/compose.yaml against the Compose Specification, and its settings against the docs.

No Docker engine runs on the development machines, so the compose file is checked
offline: against the official JSON schema (vendored in ``data/``), and for the
properties the deployment relies on (one image, shared volume at one path, health
checks, scalable workers, every ORCHARD_* variable documented).
"""

from __future__ import annotations

import copy
import json
import os
import re
from pathlib import Path

import jsonschema
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = ROOT / "docker" / "compose.yaml"
README = ROOT / "docker" / "README.md"
ENTRYPOINT = ROOT / "docker" / "entrypoint.sh"
SCHEMA = Path(__file__).parent / "data" / "compose-spec.json"

_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?::?-([^}]*))?\}")


def _interpolate(value, env: dict[str, str]):
    """Compose-style ``${VAR}`` / ``${VAR:-default}`` substitution, recursively."""
    if isinstance(value, dict):
        return {k: _interpolate(v, env) for k, v in value.items()}
    if isinstance(value, list):
        return [_interpolate(v, env) for v in value]
    if isinstance(value, str):
        whole = _VAR.fullmatch(value)
        out = _VAR.sub(lambda m: env.get(m.group(1), m.group(2) or ""), value)
        # A whole-value number (replicas: ${N:-2}) becomes a number, as compose does.
        if whole and re.fullmatch(r"-?\d+", out):
            return int(out)
        return out
    return value


@pytest.fixture(scope="module")
def schema() -> dict:
    return json.loads(SCHEMA.read_text())


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def _errors(schema: dict, doc) -> list[str]:
    validator = jsonschema.Draft7Validator(schema, format_checker=jsonschema.FormatChecker())
    return [f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(doc)]


def test_vendored_schema_is_the_compose_spec(schema):
    assert schema["title"] == "Compose Specification"
    jsonschema.Draft7Validator.check_schema(schema)
    assert (SCHEMA.parent / "LICENSE.compose-spec").read_text().lstrip().startswith("Apache License")


def test_compose_file_is_valid_as_written(schema, compose):
    assert _errors(schema, compose) == []


def test_compose_file_is_valid_with_defaults_expanded(schema, compose):
    expanded = _interpolate(compose, env={})
    assert _errors(schema, expanded) == []
    assert expanded["services"]["worker"]["deploy"]["replicas"] == 2


def test_schema_rejects_a_broken_compose_file(schema, compose):
    """The validation above can fail: a misspelt key or a wrong type is reported."""
    broken = copy.deepcopy(compose)
    broken["services"]["api"]["healthcheck"]["intervall"] = "10s"
    broken["services"]["worker"]["deploy"]["replicas"] = [2]
    errors = _errors(schema, broken)
    assert any("intervall" in e for e in errors)
    assert any("replicas" in e for e in errors)


def test_three_roles_from_one_image(compose):
    services = compose["services"]
    assert set(services) == {"api", "scheduler", "worker"}
    images = {s["image"] for s in services.values()}
    assert len(images) == 1
    for s in services.values():
        assert s["build"]["dockerfile"] == "docker/Dockerfile"
        assert (COMPOSE.parent / s["build"]["context"] / s["build"]["dockerfile"]).is_file()
    assert services["api"]["command"] == ["api"]
    assert services["scheduler"]["command"] == ["scheduler"]
    assert services["worker"]["command"] == ["worker"]


def test_every_role_has_a_health_check(compose):
    for name, s in compose["services"].items():
        test = s["healthcheck"]["test"]
        assert test[0] == "CMD"
        assert test[-2:] == ["health", name], name


def test_shared_volume_at_one_path(compose):
    assert "orchard-data" in compose["volumes"]
    mounts = {name: s["volumes"] for name, s in compose["services"].items()}
    for name, vols in mounts.items():
        assert "orchard-data:/data" in vols, name
        assert s_env(compose, name)["ORCHARD_DATA_DIR"] == "/data"


def s_env(compose: dict, name: str) -> dict:
    return compose["services"][name]["environment"]


def test_api_and_workers_use_the_scheduler_service(compose):
    for name in ("api", "worker"):
        assert s_env(compose, name)["ORCHARD_SCHEDULER"] == "tcp://scheduler:8786"
    assert s_env(compose, "scheduler")["DASK_SCHEDULER_PORT"] == "8786"
    assert compose["services"]["api"]["depends_on"]["scheduler"]["condition"] == "service_healthy"


def test_workers_are_scalable(compose):
    worker = compose["services"]["worker"]
    assert "replicas" in worker["deploy"]
    # `--scale worker=N` is impossible with a fixed container name or a fixed host port.
    assert "container_name" not in worker
    assert "ports" not in worker


def _settings_fields() -> list[str]:
    from service import settings

    return [f"ORCHARD_{name.upper()}" for name in settings.Settings.model_fields]


def _documented() -> set[str]:
    return set(re.findall(r"`((?:ORCHARD|DASK)_[A-Z0-9_]+)`", README.read_text()))


def test_every_service_setting_is_documented():
    missing = [v for v in _settings_fields() if v not in _documented()]
    assert missing == [], f"document these in docker/README.md: {missing}"


def test_every_variable_compose_and_entrypoint_use_is_documented(compose):
    used = set(re.findall(r"\b((?:ORCHARD|DASK)_[A-Z0-9_]+)\b", COMPOSE.read_text() + ENTRYPOINT.read_text()))
    missing = sorted(used - _documented())
    assert missing == [], f"document these in docker/README.md: {missing}"


def test_api_environment_names_real_settings(compose):
    """A misspelt ORCHARD_* variable in compose would be silently ignored by the service."""
    fields = set(_settings_fields())
    api_vars = {k for k in s_env(compose, "api") if k.startswith("ORCHARD_")}
    assert api_vars - fields == set()


def test_api_environment_builds_valid_settings(compose, monkeypatch):
    from service import settings

    env = _interpolate(s_env(compose, "api"), env={})
    for key in list(os.environ):
        if key.startswith("ORCHARD_"):
            monkeypatch.delenv(key)
    for key, value in env.items():
        monkeypatch.setenv(key, str(value))
    s = settings.Settings()
    assert str(s.data_dir) == "/data"
    assert s.scheduler == "tcp://scheduler:8786"
    assert s.host == "0.0.0.0" and s.port == 8000
