"""Fixtures: the real ``mcapi serve`` binary on free ports, and clients of it.

The binary is the path in ``MCAPI_BIN`` (``make python-test`` passes the
debug build), else ``target/release/mcapi`` at the repository root. Each server gets a
temporary data directory; flags the binary does not know yet (``--store
redb``, ``--api-key``) are detected from ``mcapi serve --help``.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import inspect
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Coroutine, Iterator, Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any, TypeVar

import httpx
import pytest

from mcapi_client import AsyncClient, AsyncGrpcClient, Client, GrpcClient

REPO_ROOT = Path(__file__).resolve().parents[3]
PACKAGE_ROOT = Path(__file__).resolve().parents[1]
BINARY = Path(os.environ.get("MCAPI_BIN", REPO_ROOT / "target" / "release" / "mcapi"))
STARTUP_TIMEOUT = 30.0


@cache
def serve_help() -> str:
    """The binary's ``serve --help`` text."""
    if not BINARY.exists():
        pytest.fail(
            f"the server binary {BINARY} does not exist: build it with "
            "`cargo build --release --locked` (or set MCAPI_BIN)",
            pytrace=False,
        )
    out = subprocess.run(
        [str(BINARY), "serve", "--help"], capture_output=True, text=True, timeout=30, check=True
    )
    return out.stdout


def supports_api_keys() -> bool:
    """Whether ``mcapi serve`` takes ``--api-key``."""
    return "--api-key" in serve_help()


def _store_args(data_dir: Path) -> list[str]:
    args = ["--data-dir", str(data_dir)]
    # clap lists the values of --store as "- redb: ..." lines.
    if re.search(r"^\s*-\s*redb\b", serve_help(), re.MULTILINE):
        args += ["--store", "redb"]
    return args


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Server:
    """A running ``mcapi serve``."""

    http_url: str
    grpc_target: str
    process: subprocess.Popen[bytes]
    log: Path

    def log_tail(self, lines: int = 40) -> str:
        """The last lines of the server's log."""
        return "\n".join(self.log.read_text(errors="replace").splitlines()[-lines:])

    def stop(self) -> None:
        """SIGTERM, then SIGKILL if it does not stop within 10 s."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


def start_server(
    workdir: Path,
    extra: Sequence[str] = (),
    env: dict[str, str] | None = None,
    ports: tuple[int, int] | None = None,
) -> Server:
    """Starts the binary on free ports (or on ``ports``, REST and gRPC: a
    restart where the clients connected) and waits until REST answers
    ``/readyz`` and the gRPC port accepts connections."""
    workdir.mkdir(parents=True, exist_ok=True)
    # Nothing from the caller's environment configures the server under test.
    base_env = {k: v for k, v in os.environ.items() if not k.startswith("MCAPI_")}
    base_env.update(env or {})
    last_error = ""
    for attempt in range(5):
        http_port, grpc_port = ports or (_free_port(), _free_port())
        if http_port == grpc_port:
            continue
        log = workdir / f"server-{attempt}.log"
        args = [
            str(BINARY),
            "serve",
            "--http",
            f"127.0.0.1:{http_port}",
            "--grpc",
            f"127.0.0.1:{grpc_port}",
            "--workers",
            "2",
            *_store_args(workdir / "data"),
            *extra,
        ]
        with log.open("wb") as out:
            process = subprocess.Popen(args, stdout=out, stderr=subprocess.STDOUT, env=base_env)
        server = Server(f"http://127.0.0.1:{http_port}", f"127.0.0.1:{grpc_port}", process, log)
        deadline = time.monotonic() + STARTUP_TIMEOUT
        while time.monotonic() < deadline and process.poll() is None:
            try:
                if httpx.get(f"{server.http_url}/readyz", timeout=1.0).status_code == 200:
                    with socket.create_connection(("127.0.0.1", grpc_port), timeout=1.0):
                        return server
            except (httpx.HTTPError, OSError):
                pass
            time.sleep(0.05)
        server.stop()
        last_error = server.log_tail()
        if "bind" not in last_error.lower() and "in use" not in last_error.lower():
            break  # not a port race: retrying will not help
    pytest.fail(f"mcapi serve did not become ready:\n{last_error}", pytrace=False)


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """One server for the whole run, without API keys."""
    srv = start_server(tmp_path_factory.mktemp("mcapi"))
    yield srv
    srv.stop()
    assert srv.process.returncode == 0, f"server exited with {srv.process.returncode}:\n{srv.log_tail()}"


@pytest.fixture
def client(server: Server) -> Iterator[Client]:
    """A REST client of the shared server."""
    with Client(server.http_url, timeout=30.0) as c:
        yield c


@pytest.fixture
def grpc_client(server: Server) -> Iterator[GrpcClient]:
    """A gRPC client of the shared server."""
    with GrpcClient(server.grpc_target, timeout=30.0) as c:
        yield c


@pytest.fixture
def anyio_backend() -> str:
    """AsyncClient tests run on asyncio (a loop per test: REST only, see
    :func:`run_async` for grpc.aio)."""
    return "asyncio"


@pytest.fixture
def examples_path() -> Iterator[Path]:
    """The examples folder, importable for the duration of a test."""
    path = PACKAGE_ROOT / "examples"
    sys.path.insert(0, str(path))
    try:
        yield path
    finally:
        sys.path.remove(str(path))


# grpc.aio delivers a call's completions to the event loop the call was made
# in, even after the call is cancelled (gRPC's core completes it later); a
# completion arriving once that loop is closed raises "Event loop is closed"
# inside whichever loop handles gRPC's events next, which fails the test
# running then. So every test using grpc.aio runs on this one loop, closed
# only at exit, rather than on a loop per test.
_SHARED_LOOP: asyncio.AbstractEventLoop | None = None

T = TypeVar("T")


def run_async(coro: Coroutine[Any, Any, T]) -> T:
    """Runs a coroutine to completion on the tests' one shared event loop."""
    global _SHARED_LOOP
    if _SHARED_LOOP is None:
        _SHARED_LOOP = asyncio.new_event_loop()
    return _SHARED_LOOP.run_until_complete(coro)


def async_test(fn: Callable[..., Coroutine[Any, Any, None]]) -> Callable[..., None]:
    """An ``async def`` test run on the shared loop (fixtures as usual)."""

    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> None:
        run_async(fn(*args, **kwargs))

    return run


class Blocking:
    """An asyncio client driven from synchronous test code: each coroutine
    method runs to completion on the shared event loop, so a test written
    against the blocking clients runs unchanged over the async ones."""

    def __init__(self, make: Callable[[], Any]) -> None:
        async def create() -> Any:
            return make()  # grpc.aio channels belong to the loop they are made in

        self.client = run_async(create())

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self.client, name)
        if not inspect.iscoroutinefunction(attr):
            return attr

        def call(*args: Any, **kwargs: Any) -> Any:
            return run_async(attr(*args, **kwargs))

        return call

    def close(self) -> None:
        """Closes the client."""
        run_async(self.client.aclose())


CLIENT_KINDS = ["rest", "grpc", "async-rest", "async-grpc"]
"""The four clients: REST and gRPC, blocking and asyncio."""


@contextlib.contextmanager
def open_client(kind: str, server: Server, **kw: Any) -> Iterator[Any]:
    """A client of ``server`` of one of :data:`CLIENT_KINDS`; the async ones
    wrapped in :class:`Blocking`."""
    if kind == "rest":
        with Client(server.http_url, **kw) as c:
            yield c
    elif kind == "grpc":
        with GrpcClient(server.grpc_target, **kw) as g:
            yield g
    else:
        if kind == "async-rest":
            wrapped = Blocking(lambda: AsyncClient(server.http_url, **kw))
        else:
            wrapped = Blocking(lambda: AsyncGrpcClient(server.grpc_target, **kw))
        try:
            yield wrapped
        finally:
            wrapped.close()


@pytest.fixture(params=CLIENT_KINDS)
def any_client(request: pytest.FixtureRequest, server: Server) -> Iterator[Any]:
    """Each of the four clients in turn (async ones made blocking): a test
    using it runs over REST and gRPC, blocking and asyncio."""
    with open_client(request.param, server) as c:
        yield c
