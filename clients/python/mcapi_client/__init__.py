"""Python client of mcapi: motivated RL agents (MCA-PI) as sessions.

An mcapi server hosts agents whose drive balances several kinds of stimulus.
Your program simulates (or runs) the world: it creates a session from an
environment model, then tells the session each state the agent arrives in
and the stimulus it received there, and the session answers with the next
action, the drive and the reward.

- :class:`Client` and :class:`AsyncClient`: the REST API (httpx; the
  ``rest`` extra).
- :class:`GrpcClient` and :class:`AsyncGrpcClient`: the gRPC API (grpcio;
  the ``grpc`` extra), with ``interact`` (a bidirectional stream for
  high-rate loops) and ``watch``.
- :mod:`mcapi_client.models`: model builders (hallway, grid maps, transition
  tables, Gymnasium toy-text environments, learned models, discrete
  MO-Gymnasium environments with their step adapter).
- Continuous worlds: a session created on a :class:`ContinuousModel` (a box
  of observation vectors) takes ``observation=[x1, ..., xd]`` instead of
  ``state``; ``models.from_gymnasium`` and ``models.from_mo_gymnasium`` make
  one of a ``Box``-observation environment (:mod:`mcapi_client.continuous`).
- :mod:`mcapi_client.groups`: session groups, N agents of one model stepped
  by columns (numpy arrays; the ``vector`` extra), from ``create_group`` of
  any of the four clients; :mod:`mcapi_client.vector_env` drives a Gymnasium
  vector environment with one.
- :mod:`mcapi_client.errors`: :class:`McapiError` and its subclasses, one per
  family of the server's stable error codes.
- Curiosity: ``create_session(..., curiosity=CuriosityConfig(signal_dim=2))``
  adds a ``curiosity`` stimulus the server computes from raw ``signal=``
  samples sent with observations; see :class:`CuriosityConfig`,
  :class:`TickCuriosity` and :class:`CuriosityInfo`.
- Delivery: the clients number each session's observations (``seq``) and
  send them again after a lost answer or a broken ``interact`` stream; the
  server applies each once and replays its recorded reply
  (``step.replayed``). ``exactly_once=False`` turns the numbering off;
  ``retry=`` (:class:`RetryPolicy`) sets the retries, and
  ``client.retries`` (:class:`RetryCounter`) counts them.
- Agent options: the keywords of ``create_session`` (``seed``, ``eta``,
  ``curiosity``, ...) are those of :class:`AgentKwargs`, one per parameter
  of the server, named in order by :data:`AGENT_OPTIONS`.

The core (types, models, errors) needs no third-party package; each
transport is imported when first used, and without its packages installed
that raises an :class:`ImportError` saying how to install them (a plain
``pip install './clients/python'`` from the mcapi repository has REST;
``'./clients/python[grpc]'`` adds gRPC). Every
method takes numpy integer and float scalars and arrays where it takes
numbers.

    from mcapi_client import Client, models

    world = models.hallway()
    with Client("http://127.0.0.1:8080") as mc:
        session = mc.create_session(world, seed=7)
        step = mc.observe(session.id, state=25)
        step = mc.observe(session.id, state=26, stimulus=world.stimulus(26))
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from . import models
from .continuous import ContinuousModel
from .errors import (
    BadRequest,
    Forbidden,
    InternalError,
    InvalidModel,
    InvalidObservation,
    InvalidParameter,
    LimitExceeded,
    McapiError,
    MoveConflict,
    NotFound,
    PayloadTooLarge,
    QuotaExceeded,
    SequenceRefused,
    SessionFailed,
    Timeout,
    TooManySessions,
    TooManyStreams,
    TransportError,
    Unauthenticated,
    Unavailable,
    UnknownRoute,
    WrongReplica,
)
from .retry import DEFAULT_RETRY, RetryCounter, RetryPolicy
from .types import (
    AGENT_OPTIONS,
    AgentConfig,
    AgentKwargs,
    AgentOptions,
    BasisSummary,
    ContinuousStats,
    CuriosityConfig,
    CuriosityInfo,
    FrozenModule,
    GridLayout,
    HistoryEntry,
    LearnedSummary,
    ModelSummary,
    Observation,
    SessionCost,
    SessionInfo,
    SessionPage,
    SessionStats,
    SessionSummary,
    Step,
    TickCuriosity,
    Values,
)

if TYPE_CHECKING:
    from .grpc_client import (
        AsyncBatchInteraction,
        AsyncGrpcClient,
        AsyncInteraction,
        AsyncWatch,
        BatchInteraction,
        GrpcClient,
        Interaction,
        Watch,
    )
    from .rest import AsyncClient, Client

# The transports, imported on first use (each needs its extra).
_TRANSPORTS = {
    "Client": "rest",
    "AsyncClient": "rest",
    "GrpcClient": "grpc_client",
    "AsyncGrpcClient": "grpc_client",
    "Interaction": "grpc_client",
    "AsyncInteraction": "grpc_client",
    "BatchInteraction": "grpc_client",
    "AsyncBatchInteraction": "grpc_client",
    "Watch": "grpc_client",
    "AsyncWatch": "grpc_client",
}


def __getattr__(name: str) -> Any:
    module = _TRANSPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_TRANSPORTS))


__version__ = "0.1.0"
"""The version of this package."""

__all__ = [
    "Client",
    "AsyncClient",
    "GrpcClient",
    "AsyncGrpcClient",
    "Interaction",
    "AsyncInteraction",
    "BatchInteraction",
    "AsyncBatchInteraction",
    "Watch",
    "AsyncWatch",
    "models",
    "ContinuousModel",
    "McapiError",
    "BadRequest",
    "InvalidModel",
    "InvalidParameter",
    "InvalidObservation",
    "Unauthenticated",
    "Forbidden",
    "NotFound",
    "UnknownRoute",
    "LimitExceeded",
    "PayloadTooLarge",
    "TooManySessions",
    "TooManyStreams",
    "QuotaExceeded",
    "SessionFailed",
    "MoveConflict",
    "SequenceRefused",
    "Unavailable",
    "TransportError",
    "WrongReplica",
    "Timeout",
    "InternalError",
    "RetryPolicy",
    "RetryCounter",
    "DEFAULT_RETRY",
    "AgentConfig",
    "AgentKwargs",
    "AGENT_OPTIONS",
    "AgentOptions",
    "BasisSummary",
    "ContinuousStats",
    "CuriosityConfig",
    "CuriosityInfo",
    "FrozenModule",
    "GridLayout",
    "HistoryEntry",
    "ModelSummary",
    "LearnedSummary",
    "Observation",
    "SessionInfo",
    "SessionPage",
    "SessionCost",
    "SessionStats",
    "SessionSummary",
    "Step",
    "TickCuriosity",
    "Values",
    "__version__",
]
