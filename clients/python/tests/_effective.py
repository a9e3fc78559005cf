"""A session's effective agent configuration as the server sends it, built
from the generated table (``AGENT_OPTIONS``, ``AGENT_KINDS``): a value per
kind for every option a test does not name, so that adding an option to the
server's table needs no edit here or in the tests using these.

Over REST it is the ``"agent"`` object (:func:`effective_json`); over gRPC an
``EffectiveConfig`` (:func:`effective_message`), encoded here by the proto's
own conventions, not by the client's encoder under test.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from mcapi_client._params import AGENT_KINDS, AGENT_OPTIONS
from mcapi_client._proto.mcapi.v1 import agents_pb2 as pb


def of_kind(kind: str) -> list[str]:
    """The options of ``kind``, in the server's order."""
    return [name for name in AGENT_OPTIONS if AGENT_KINDS[name] == kind]


def _enum_values(field: str) -> dict[str, int]:
    """The names of a proto enum field's values, as the client and the REST
    API spell them (``UPDATE_MODE_ASYNC`` is ``"async"``), but the zero one."""
    enum = pb.EffectiveConfig.DESCRIPTOR.fields_by_name[field].enum_type
    prefix = enum.values_by_number[0].name.removesuffix("UNSPECIFIED")
    return {v.name.removeprefix(prefix).lower(): v.number for v in enum.values if v.number != 0}


def _first_name(field: str) -> str:
    return next(iter(_enum_values(field)))


def value_of_kind(name: str) -> Any:
    """A valid effective value of the option ``name``, by its kind; ``None``
    for an "object" (the server leaves one out when unset)."""
    kind = AGENT_KINDS[name]
    if kind == "real":
        return 0.5
    if kind == "integer":
        return 3
    if kind == "per_stimulus":
        return [1.0]
    if kind == "real_or_name":
        return _first_name(f"{name}_rule")  # "sample_mean" for stimulus_rate
    if kind == "choice":
        return _first_name(name)  # "lockstep" for update_mode
    if kind == "object":
        return None
    raise AssertionError(f"agent option `{name}` has a kind these tests do not know: {kind}")


def effective_json(**given: Any) -> dict[str, Any]:
    """The ``"agent"`` object of a session: ``given`` as given, every other
    option the value of its kind (an "object" left out)."""
    unknown = set(given) - set(AGENT_OPTIONS)
    assert not unknown, f"not agent options: {sorted(unknown)}"
    d = {name: value_of_kind(name) for name in AGENT_OPTIONS}
    d.update(given)
    return {name: value for name, value in d.items() if value is not None}


def effective_message(d: Mapping[str, Any], **fields: Any) -> pb.EffectiveConfig:
    """The ``EffectiveConfig`` the gRPC server sends for the ``"agent"`` object
    ``d``: ``fields`` (proto field names) as given, every option they do not
    set encoded from ``d`` by its kind (an "object" left unset)."""
    m = pb.EffectiveConfig(**fields)
    desc = pb.EffectiveConfig.DESCRIPTOR
    set_by_hand = set()
    for field in fields:
        oneof = desc.fields_by_name[field].containing_oneof
        set_by_hand.add(oneof.name if oneof is not None else field)
    for name in AGENT_OPTIONS:
        value, kind = d.get(name), AGENT_KINDS[name]
        if name in set_by_hand or value is None:
            continue
        if kind == "real":
            setattr(m, name, float(value))
        elif kind == "integer":
            setattr(m, name, int(value))
        elif kind == "per_stimulus":
            getattr(m, name).extend(float(x) for x in value)
        elif kind == "real_or_name" and isinstance(value, str):
            setattr(m, f"{name}_rule", _enum_values(f"{name}_rule")[value])
        elif kind == "real_or_name":
            setattr(m, f"{name}_constant", float(value))
        elif kind == "choice":
            setattr(m, name, _enum_values(name)[value])
        else:
            raise AssertionError(f"set the {kind} option `{name}` of the message by hand")
    return m
