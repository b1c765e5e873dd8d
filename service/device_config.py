"""A cell's device configuration: one typed, frozen model of its ``devices`` document (the fake
cell's endpoint line, contracts §7, or the same shape for real equipment) and its one parser.

:func:`parse_devices` is the only reader of the document: registration and edits (strict: an
unknown key is refused with "did you mean"), the sessions that open the devices, the connection
test, the overview and the certificate (:func:`stored_devices`). Its JSON Schema
(:func:`devices_json_schema`) is served at ``GET /api/v1/schemas/devices``; the web page builds
and checks its device fields from it, so that the patterns and the words of the errors below are
the page's too.

The model names the devices and their addresses; how long to wait for them is the service's
(``device_timeout_s``, the connection test's limit), given when they are opened (``devices.py``).
"""

from __future__ import annotations

import difflib
import typing
from typing import Any

from pydantic import BaseModel, ValidationError

from .device_fields import (
    DEFAULT_BALL_RADIUS_M,
    HOST_OPTIONAL_PORT_PATTERN,
    HOST_PATTERN,
    HOST_PORT_PATTERN,
    SERIAL_URL_PATTERN,
    CanBus,
    DeviceConfigError,
    EmsconSettings,
)
from .device_registry import DEVICES, DevicesConfig

__all__ = [
    "DEFAULT_BALL_RADIUS_M",
    "DEVICES",
    "HOST_OPTIONAL_PORT_PATTERN",
    "HOST_PATTERN",
    "HOST_PORT_PATTERN",
    "SERIAL_URL_PATTERN",
    "CanBus",
    "DeviceConfigError",
    "DevicesConfig",
    "EmsconSettings",
    "devices_json_schema",
    "parse_devices",
    "stored_devices",
]

# --------------------------------------------------------------------------- the parser

_TYPES = {
    "string_type": "a string",
    "int_type": "an integer",
    "float_type": "a number",
    "bool_type": "true or false",
    "dict_type": "an object",
    "model_type": "an object",
    "literal_error": None,
}


def parse_devices(doc: Any, *, stored: bool = False) -> DevicesConfig:
    """The cell's devices from its ``devices`` document. Raises :class:`DeviceConfigError`
    naming the field (``devices.modbus: expected HOST:PORT, e.g. 192.168.1.10:502, got 'x'``).

    An absent device may also be written ``null`` or ``""`` (the page's empty fields). A key
    the model does not know is refused, with the nearest known one ("did you mean"), unless
    ``stored``: a cell's stored document, registered before the check, is read with unknown keys
    left out, so that its sessions run as they did.
    """
    if doc is None:
        doc = {}
    if not isinstance(doc, dict):
        raise DeviceConfigError("devices", f"expected an object (the endpoint line's shape), got {doc!r}")
    doc = {k: v for k, v in doc.items() if v is not None and v != ""}
    if stored:
        doc = {k: v for k, v in doc.items() if k in DevicesConfig.model_fields}
    try:
        return DevicesConfig.model_validate(doc, context={"registering": not stored})
    except ValidationError as exc:
        raise _error(exc) from None


def stored_devices(doc: Any) -> DevicesConfig:
    """A cell's stored ``devices`` document (``Cell.devices``): :func:`parse_devices` with keys
    from before the check left out."""
    return parse_devices(doc, stored=True)


def _model_of(path: list) -> type[BaseModel] | None:
    """The model whose keys the last element of ``path`` would be one of."""
    model: Any = DevicesConfig
    for part in path:
        field = model.model_fields.get(part) if isinstance(model, type) and issubclass(model, BaseModel) else None
        if field is None:
            return None
        model = _settings_model(field.annotation)
    return model


def _settings_model(annotation: Any) -> type[BaseModel] | None:
    """The settings object a field may be written as (``emscon``'s, the CAN bus), if any."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):  # through unions and Annotated[...]
        found = _settings_model(arg)
        if found is not None:
            return found
    return None


def _error(exc: ValidationError) -> DeviceConfigError:
    err = exc.errors(include_url=False)[0]
    # without the emscon form's tags, and a dict's key named as its entry
    loc = [str(p) for p in err["loc"] if p not in ("address", "settings", "[key]")]
    kind, value = err["type"], err.get("input")
    message = err["msg"]
    if kind == "extra_forbidden":
        known = list((_model_of(loc[:-1]) or DevicesConfig).model_fields)
        near = difflib.get_close_matches(loc[-1], known, n=1, cutoff=0.6)
        message = (
            "unknown key" + (f"; did you mean {near[0]!r}?" if near else "") + f" (expected one of {', '.join(known)})"
        )
    elif kind == "missing":
        message = "missing"
    elif kind == "value_error":
        message = str(err["ctx"]["error"])
        if message.startswith("["):  # a model rule naming its field: "[host] missing; ..."
            name, _, message = message[1:].partition("] ")
            loc = [*loc, *name.split(".")]
    elif kind == "literal_error":
        message = f"expected {err['ctx']['expected']}, got {value!r}"
    elif kind in _TYPES:
        message = f"expected {_TYPES[kind]}, got {value!r}"
    elif kind in ("greater_than_equal", "less_than_equal", "greater_than", "less_than"):
        message = f"{message.replace('Input should be', 'expected a number')}, got {value!r}"
    elif kind == "emscon_form":
        message = f"{message}, got {value!r}"
    elif kind == "string_too_short":
        message = f"expected a non-empty string, got {value!r}"
    elif kind == "string_pattern_mismatch" and loc[:1] in (["encoders"], ["resolvers"]):
        message = f"expected a joint number (1, 2, ...), got {value!r}"
    return DeviceConfigError(".".join(["devices", *loc]), message)


def devices_json_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of a cell's ``devices`` document, as the page reads it.
    ``x-devices``: the registry's entries in its order (key, role, label, the page's kind of
    field), from which the page builds the device form and names the devices; each device's
    property carries its ``x-label`` too."""
    schema = DevicesConfig.model_json_schema(mode="validation")
    for entry in DEVICES:
        schema["properties"][entry.key]["x-label"] = entry.label
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        **schema,
        "x-devices": [e.describe() for e in DEVICES],
    }
