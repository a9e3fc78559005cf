"""Python client of mcapi: motivated RL agents (MCA-PI) as sessions.

An mcapi server hosts agents whose drive balances several kinds of stimulus.
Your program simulates (or runs) the world: it creates a session from an
environment model, then tells the session each state the agent arrives in
and the stimulus it received there, and the session answers with the next
action, the drive and the reward.

- :class:`Client` and :class:`AsyncClient`: the REST API (httpx).
- :class:`GrpcClient`: the gRPC API, with :meth:`GrpcClient.interact` (a
  bidirectional stream for high-rate loops) and :meth:`GrpcClient.watch`.
- :mod:`mcapi_client.models`: model builders (hallway, grid maps, transition
  tables, Gymnasium toy-text environments).
- :mod:`mcapi_client.errors`: :class:`McapiError` and its subclasses, one per
  family of the server's stable error codes.
- Curiosity: ``create_session(..., curiosity=CuriosityConfig(signal_dim=2))``
  adds a ``curiosity`` stimulus the server computes from raw ``signal=``
  samples sent with observations; see :class:`CuriosityConfig`,
  :class:`TickCuriosity` and :class:`CuriosityInfo`.

    from mcapi_client import Client, models

    world = models.hallway()
    with Client("http://127.0.0.1:8080") as mc:
        session = mc.create_session(world, seed=7)
        step = mc.observe(session.id, state=25)
        step = mc.observe(session.id, state=26, stimulus=world.stimulus(26))
"""

from . import models
from .errors import (
    BadRequest,
    InternalError,
    InvalidModel,
    InvalidObservation,
    InvalidParameter,
    LimitExceeded,
    McapiError,
    NotFound,
    PayloadTooLarge,
    Timeout,
    TooManySessions,
    TooManyStreams,
    QuotaExceeded,
    SessionFailed,
    TransportError,
    Unauthenticated,
    Unavailable,
    UnknownRoute,
)
from .grpc_client import GrpcClient, Interaction, Watch
from .rest import AsyncClient, Client
from .types import (
    AgentConfig,
    AgentOptions,
    BasisSummary,
    CuriosityConfig,
    CuriosityInfo,
    FrozenModule,
    GridLayout,
    HistoryEntry,
    ModelSummary,
    Observation,
    SessionInfo,
    SessionPage,
    SessionCost,
    SessionStats,
    SessionSummary,
    Step,
    TickCuriosity,
    Values,
)

__version__ = "0.1.0"
"""The version of this package."""

__all__ = [
    "Client",
    "AsyncClient",
    "GrpcClient",
    "Interaction",
    "Watch",
    "models",
    "McapiError",
    "BadRequest",
    "InvalidModel",
    "InvalidParameter",
    "InvalidObservation",
    "Unauthenticated",
    "NotFound",
    "UnknownRoute",
    "LimitExceeded",
    "PayloadTooLarge",
    "TooManySessions",
    "TooManyStreams",
    "QuotaExceeded",
    "SessionFailed",
    "Unavailable",
    "TransportError",
    "Timeout",
    "InternalError",
    "AgentConfig",
    "AgentOptions",
    "BasisSummary",
    "CuriosityConfig",
    "CuriosityInfo",
    "FrozenModule",
    "GridLayout",
    "HistoryEntry",
    "ModelSummary",
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
