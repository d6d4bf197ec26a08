"""Backend configs: one pydantic model per backend, chosen by its ``backend`` key.

A config section that picks a backend (``keyframe_vl.segmenter``, ``keyframe_vl.vl``,
``tracker.features``) holds only that backend's fields. Its model is looked up by ``backend``
in the registry of its kind (a discriminated union whose members are the registry's entries,
so a backend registered later, by a plugin or a test, is a member too), validated with that
model's own fields, and builds the object it describes (``cfg.build(...)``), importing the
heavy libraries only then.

Adding a backend is its config model, decorated with ``@REGISTRY.register("name")``, with a
``build`` method, and the implementation module that ``build`` imports.
"""

from __future__ import annotations

from abc import abstractmethod
from typing import Annotated, Any

from pydantic import BeforeValidator, Field, SerializeAsAny

from shared.config.base import StrictModel
from shared.registry import Registry


class BackendConfig(StrictModel):
    """A backend's settings; subclasses fix ``backend`` to their registered name."""

    backend: str
    """Which implementation; the other keys of the section are that backend's."""

    @abstractmethod
    def build(self, *args: Any, **kwargs: Any) -> Any:
        """The object this config describes."""


def backend_section(registry: Registry, base: type[BackendConfig], default: str):
    """The annotation of a config field whose model is picked by ``backend`` from ``registry``
    (``default`` when the key is absent), and the field's default (that backend's defaults)."""

    def pick(value: Any) -> Any:
        if isinstance(value, base):
            return value
        if isinstance(value, dict):
            name = value.get("backend", default)
            model = registry.get(name)  # UnknownName (a ValueError) names the choices
            return model.model_validate({**value, "backend": name})
        return value

    # Error messages find the model a section's ``backend`` asks for through these.
    base.__registry__ = registry
    base.__default_backend__ = default
    annotation = Annotated[SerializeAsAny[base], BeforeValidator(pick)]
    return annotation, Field(default_factory=lambda: registry.get(default)())


def backend_model(registry: Registry, data: Any, default: str | None = None) -> type[BackendConfig] | None:
    """The registered model ``data`` (a section's raw mapping) asks for, or None."""
    name = data.get("backend", default) if isinstance(data, dict) else None
    if name is None or name not in registry:
        return None
    return registry.get(name)


def backend_config(registry: Registry, default: str, **fields: Any) -> BackendConfig:
    """The config of the backend ``fields["backend"]`` names (``default`` when absent), with
    ``fields`` validated by that backend's model: what a section of a YAML file becomes."""
    name = fields.get("backend", default)
    return registry.get(name).model_validate({**fields, "backend": name})
