"""Strict pydantic base and YAML loading with errors that name the file and the key."""

from __future__ import annotations

import copy
import difflib
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import yaml
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError

from shared.devices import DEVICE_PATTERN


class StrictModel(BaseModel):
    """Base of every config model: unknown keys are errors, docstrings become descriptions."""

    model_config = ConfigDict(
        extra="forbid",
        validate_assignment=True,
        use_attribute_docstrings=True,
        frozen=False,
    )


Device = Annotated[str, Field(pattern=DEVICE_PATTERN)]
"""A torch device: ``auto`` (CUDA when torch sees a GPU), ``cpu``, ``cuda`` or ``cuda:N``."""

Precision = Literal["auto", "fp32", "fp16", "bf16"]
"""A model's numeric precision; ``auto`` is fp16 on CUDA and fp32 on a CPU (shared/devices.py)."""


def _registered_service(name: str) -> str:
    from shared.registry import SERVICES

    if name not in SERVICES:
        raise ValueError(SERVICES.unknown(name))
    return name


ServiceName = Annotated[str, AfterValidator(_registered_service)]
"""A service of the services registry (shared/registry.py): ``source``, ``tracker``, ..."""


class ConfigError(ValueError):
    """A config file could not be read or does not validate. The message names file and key."""


M = TypeVar("M", bound=BaseModel)


def _model_at(model: type[BaseModel] | None, path: tuple, data: Any = None) -> type[BaseModel] | None:
    """The nested model at ``path``; where a section picks its model by ``backend`` (a backend
    config, shared/config/backends.py), the one the raw ``data`` asks for."""
    for part in path:
        if model is None:
            return None
        field = model.model_fields.get(str(part))
        ann = getattr(field, "annotation", None)
        model = ann if isinstance(ann, type) and issubclass(ann, BaseModel) else None
        data = data.get(str(part)) if isinstance(data, dict) else None
        if model is not None and "backend" in model.model_fields:
            # A section not in the data yet takes its default backend.
            model = _backend_of(model, data if isinstance(data, dict) else {}) or model
    return model


def _backend_of(base: type[BaseModel], data: dict) -> type[BaseModel] | None:
    from shared.config.backends import BackendConfig

    registry = getattr(base, "__registry__", None)
    if not issubclass(base, BackendConfig) or registry is None:
        return None
    name = data.get("backend", getattr(base, "__default_backend__", None))
    return registry.get(name) if name in registry else None


def format_validation_error(err: ValidationError, source: str, model: type[BaseModel] | None = None, data: Any = None) -> str:
    """One line per problem: ``SOURCE: dotted.key: what was expected (got VALUE)``. An unknown
    key of a backend's section names the backend and suggests the nearest of its own keys."""
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"]) or "<root>"
        if e["type"] == "extra_forbidden":
            at = _model_at(model, e["loc"][:-1], data)
            close = difflib.get_close_matches(str(e["loc"][-1]), list(at.model_fields) if at else [], n=1)
            whose = ""
            if at is not None and "backend" in at.model_fields:
                whose = f" for backend {at.model_fields['backend'].default!r}"
            msg = f"unknown key{whose}" + (f" (did you mean {close[0]!r}?)" if close else "")
        else:
            msg = e["msg"]
        got = e.get("input")
        shown = "" if e["type"] in ("extra_forbidden", "missing") else f" (got {got!r})"
        if len(shown) > 80:
            shown = shown[:77] + "...)"
        lines.append(f"{source}: {loc}: {msg}{shown}")
    return "\n".join(lines)


def read_yaml(path: str | Path) -> dict:
    """Read a YAML mapping, or raise :class:`ConfigError` naming the file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config file ({exc.strerror or exc})") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


def validate(model: type[M], data: dict, source: str) -> M:
    """Validate ``data`` as ``model``; errors name ``source`` and every bad key."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, source, model, data)) from None


def load_model(model: type[M], path: str | Path) -> M:
    """Load one YAML file as ``model``."""
    return validate(model, read_yaml(path), str(path))


def dump_yaml(model: BaseModel) -> str:
    """The fully resolved config (defaults included) as YAML."""
    return yaml.safe_dump(model.model_dump(mode="json"), sort_keys=False)


def save_resolved(model: BaseModel, path: str | Path) -> Path:
    """Write the resolved config atomically beside a map or run, so the run can be reproduced."""
    from shared.io import atomic_write_text

    return atomic_write_text(Path(path), dump_yaml(model))


def deep_merge(base: dict, over: dict) -> dict:
    """``base`` with ``over`` laid on top, nested dicts merged key by key; both left as they were.
    A section whose ``backend`` ``over`` changes is replaced, not merged: the fields ``base``
    gave it belong to the other backend (shared/config/backends.py)."""
    out = copy.deepcopy(base)
    for key, value in over.items():
        old = out.get(key)
        if isinstance(value, dict) and isinstance(old, dict) and "backend" in value and value["backend"] != old.get("backend"):
            out[key] = copy.deepcopy(value)
        elif isinstance(value, dict) and isinstance(old, dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out
