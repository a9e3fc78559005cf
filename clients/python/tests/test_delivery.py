"""Exactly-once delivery: the clients number observations (``seq``) and send
them again after a lost answer; the server applies each once and replays its
recorded reply. Faults come from :class:`CutProxy`, a TCP proxy between the
client and the server that drops a reply on the floor and closes the
connection after the server has applied the request."""

from __future__ import annotations

import dataclasses
import logging
import random
import re
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import CLIENT_KINDS, Server, open_client, run_async, serve_help, start_server

from mcapi_client import (
    AsyncGrpcClient,
    Client,
    GrpcClient,
    Observation,
    RetryPolicy,
    SequenceRefused,
    Step,
    TransportError,
    models,
)
from mcapi_client._seq import Sequences

FAST = RetryPolicy(deadline=15.0, initial_backoff=0.02, max_backoff=0.5, rng=random.Random(1))
WORLD = models.hallway()


class CutProxy:
    """Forwards TCP connections to ``target``. After :meth:`cut`, the next
    chunk of at least ``min_bytes`` the server sends is dropped and its
    connection closed both ways: the server has done the request, the
    client never hears of it."""

    def __init__(self, target: str) -> None:
        host, port = target.rsplit(":", 1)
        self._target = (host, int(port))
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port: int = self._listener.getsockname()[1]
        self._lock = threading.Lock()
        self._cuts = 0
        self._min_bytes = 1
        self.cut_done = 0
        self._conns: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def cut(self, n: int = 1, min_bytes: int = 1) -> None:
        with self._lock:
            self._cuts, self._min_bytes = n, min_bytes

    def _take_cut(self, size: int) -> bool:
        with self._lock:
            if self._cuts > 0 and size >= self._min_bytes:
                self._cuts -= 1
                self.cut_done += 1
                return True
            return False

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            try:
                upstream = socket.create_connection(self._target)
            except OSError:
                client.close()
                continue
            for s in (client, upstream):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._conns += [client, upstream]
            threading.Thread(target=self._pipe, args=(client, upstream, False), daemon=True).start()
            threading.Thread(target=self._pipe, args=(upstream, client, True), daemon=True).start()

    def _pipe(self, src: socket.socket, dst: socket.socket, down: bool) -> None:
        try:
            while True:
                data = src.recv(65536)
                if not data or (down and self._take_cut(len(data))):
                    break
                dst.sendall(data)
        except OSError:
            pass
        self._kill(src, dst)

    @staticmethod
    def _kill(*socks: socket.socket) -> None:
        for s in socks:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()

    def close(self) -> None:
        self._listener.close()
        with self._lock:
            conns, self._conns = self._conns, []
        self._kill(*conns)


@pytest.fixture
def http_proxy(server: Server) -> Iterator[CutProxy]:
    proxy = CutProxy(server.http_url.removeprefix("http://"))
    yield proxy
    proxy.close()


@pytest.fixture
def grpc_proxy(server: Server) -> Iterator[CutProxy]:
    proxy = CutProxy(server.grpc_target)
    yield proxy
    proxy.close()


def _via(server: Server, http: CutProxy | None = None, grpc: CutProxy | None = None) -> Server:
    """The server as reached through the proxies."""
    return dataclasses.replace(
        server,
        http_url=f"http://127.0.0.1:{http.port}" if http else server.http_url,
        grpc_target=f"127.0.0.1:{grpc.port}" if grpc else server.grpc_target,
    )


def _walk(n: int) -> list[Observation]:
    """A first observation, then ``n`` moves back and forth in the hallway."""
    out = [Observation(25)]
    for i in range(n):
        state = 26 if i % 2 == 0 else 25
        out.append(Observation(state, WORLD.stimulus(state), "right" if state == 26 else "left"))
    return out


def _twin(server: Server, walk: list[Observation], seed: int) -> list[Step]:
    """The steps of the walk on a fresh session, with no faults."""
    with Client(server.http_url, exactly_once=False) as mc:
        sid = mc.create_session(WORLD, seed=seed).id
        return mc.observe_batch(sid, walk)


@pytest.mark.parametrize("kind", ["rest", "async-rest"])
def test_a_resend_after_a_cut_connection_is_replayed_not_applied(
    kind: str, server: Server, http_proxy: CutProxy, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG, logger="mcapi_client")
    walk = _walk(3)
    with open_client(kind, _via(server, http=http_proxy), retry=FAST) as mc:
        sid = mc.create_session(WORLD, seed=5).id
        steps = [mc.observe(sid, walk[0].state), mc.observe(sid, walk[1].state, walk[1].stimulus, "right")]
        http_proxy.cut(1)
        o = walk[2]
        step = mc.observe(sid, o.state, o.stimulus, o.action_taken)
        assert http_proxy.cut_done == 1
        assert step.replayed and step.tick == 2
        assert mc.retries.total == 1 and mc.retries["transport_error"] == 1
        retried = [r.getMessage() for r in caplog.records if r.name == "mcapi_client"]
        assert len(retried) == 1 and "retry 1 of POST" in retried[0], retried
        assert "transport_error" in retried[0]
        info = mc.get_session(sid)
        assert (info.tick, info.next_seq) == (2, 3)  # applied once
        steps.append(step)
        # The batch after it goes on from seq 3.
        steps += mc.observe_batch(sid, walk[3:])
        assert mc.get_session(sid).next_seq == len(walk)
    assert steps == _twin(server, walk, seed=5)


def test_without_exactly_once_a_cut_connection_is_raised(server: Server, http_proxy: CutProxy) -> None:
    """The contrast: unnumbered, the client cannot know whether the
    observation was applied, so it does not send it again."""
    with Client(_via(server, http=http_proxy).http_url, retry=FAST, exactly_once=False) as mc:
        sid = mc.create_session(WORLD, seed=5).id
        mc.observe(sid, 25)
        http_proxy.cut(1)
        with pytest.raises(TransportError):
            mc.observe(sid, 26, WORLD.stimulus(26), "right")
        assert mc.retries.total == 0
        assert mc.get_session(sid).tick == 1  # it was applied all the same


def test_after_a_lost_answer_the_same_observation_is_applied_once(
    server: Server, http_proxy: CutProxy
) -> None:
    """With retries off the lost answer is raised; the caller sending the
    same observation again gets the recorded step (seq taken again), and
    one sending another gets it applied after the lost one."""
    with Client(_via(server, http=http_proxy).http_url, retry=None) as mc:
        sid = mc.create_session(WORLD, seed=5).id
        mc.observe(sid, 25)
        http_proxy.cut(1)
        with pytest.raises(TransportError):
            mc.observe(sid, 26, WORLD.stimulus(26), "right")
        again = mc.observe(sid, 26, WORLD.stimulus(26), "right")
        assert again.replayed and again.tick == 1
        http_proxy.cut(1)
        with pytest.raises(TransportError):
            mc.observe(sid, 25, WORLD.stimulus(25), "left")
        other = mc.observe(sid, 26, WORLD.stimulus(26), "right")  # seq_conflict, read, resent
        assert not other.replayed and other.tick == 3
        assert mc.get_session(sid).next_seq == 4


@pytest.mark.parametrize("kind", ["grpc", "async-grpc"])
def test_grpc_observe_resent_after_a_cut_connection(
    kind: str, server: Server, grpc_proxy: CutProxy
) -> None:
    walk = _walk(2)
    with open_client(kind, _via(server, grpc=grpc_proxy), retry=FAST) as mc:
        sid = mc.create_session(WORLD, seed=8).id
        steps = [mc.observe(sid, 25)]
        # A reply's frames (a step is more than 30 bytes; window updates,
        # pings and settings are less) are cut after the server applied it.
        grpc_proxy.cut(1, min_bytes=30)
        o = walk[1]
        steps.append(mc.observe(sid, o.state, o.stimulus, o.action_taken))
        assert grpc_proxy.cut_done == 1
        assert mc.retries.total >= 1, mc.retries
        assert steps[-1].replayed
        o = walk[2]
        steps.append(mc.observe(sid, o.state, o.stimulus, o.action_taken))
        info = mc.get_session(sid)
        assert (info.tick, info.next_seq) == (2, 3)
    assert steps == _twin(server, walk, seed=8)


def _stream_walk(stream: Any, walk: list[Observation], proxy: CutProxy, cut_after: int) -> list[Step]:
    """Steps the walk, pipelined, cutting the connection once mid-stream."""
    steps = [stream.step(walk[0].state)]
    for i, o in enumerate(walk[1:]):
        if i == cut_after:
            proxy.cut(1, min_bytes=30)
        stream.send(o.state, o.stimulus, o.action_taken)
    return steps


def test_a_broken_interact_stream_resumes_from_the_first_unanswered_seq(
    server: Server, grpc_proxy: CutProxy
) -> None:
    walk = _walk(60)
    with GrpcClient(_via(server, grpc=grpc_proxy).grpc_target, retry=FAST) as mc:
        sid = mc.create_session(WORLD, seed=9).id
        with mc.interact(sid) as stream:
            steps = _stream_walk(stream, walk, grpc_proxy, cut_after=20)
            steps += list(stream)
            # And the reopened stream goes on.
            o = walk[1]
            extra = stream.step(o.state, o.stimulus, o.action_taken)
        assert grpc_proxy.cut_done == 1
        assert mc.retries.total >= 1, mc.retries
        assert any(s.replayed for s in steps)
        info = mc.get_session(sid)
        assert (info.tick, info.next_seq) == (len(walk), len(walk) + 1)  # each once
        assert extra.tick == len(walk)
    assert steps == _twin(server, walk, seed=9)


def test_a_broken_async_interact_stream_resumes(server: Server, grpc_proxy: CutProxy) -> None:
    walk = _walk(60)
    target = _via(server, grpc=grpc_proxy).grpc_target

    async def run() -> tuple[list[Step], int, Any]:
        async with AsyncGrpcClient(target, retry=FAST) as mc:
            sid = (await mc.create_session(WORLD, seed=10)).id
            async with mc.interact(sid) as stream:
                steps = [await stream.step(walk[0].state)]
                for i, o in enumerate(walk[1:]):
                    if i == 20:
                        grpc_proxy.cut(1, min_bytes=30)
                    stream.send(o.state, o.stimulus, o.action_taken)
                steps += [s async for s in stream]
            return steps, mc.retries.total, await mc.get_session(sid)

    steps, retries, info = run_async(run())
    assert grpc_proxy.cut_done == 1 and retries >= 1
    assert any(s.replayed for s in steps)
    assert (info.tick, info.next_seq) == (len(walk) - 1, len(walk))
    assert steps == _twin(server, walk, seed=10)


def test_an_unknown_sessions_stream_reads_its_next_seq_first(server: Server) -> None:
    """A client that did not create the session numbers from its next_seq."""
    walk = _walk(6)
    with Client(server.http_url) as other:
        sid = other.create_session(WORLD, seed=11).id
        first = other.observe_batch(sid, walk[:3])
    with GrpcClient(server.grpc_target) as mc, mc.interact(sid) as stream:
        rest = [stream.step(o.state, o.stimulus, o.action_taken) for o in walk[3:]]
        assert not any(s.replayed for s in rest)
        assert mc.get_session(sid).next_seq == len(walk)
    assert first + rest == _twin(server, walk, seed=11)


@pytest.mark.parametrize("kind", CLIENT_KINDS)
def test_seq_refusals_are_raised(kind: str, server: Server) -> None:
    walk = _walk(3)
    with open_client(kind, server) as mc:
        sid = mc.create_session(WORLD, seed=12).id
        a = mc.observe(sid, 25)
        b = mc.observe(sid, 26, walk[1].stimulus, "right")
        # A seq given by hand is sent as it is.
        with pytest.raises(SequenceRefused) as gap:
            mc.observe(sid, 25, walk[2].stimulus, "left", seq=5)
        assert (gap.value.code, gap.value.expected_seq, gap.value.seq) == ("seq_gap", 2, 5)
        with pytest.raises(SequenceRefused) as conflict:
            mc.observe(sid, 24, walk[1].stimulus, "left", seq=1)
        assert conflict.value.code == "seq_conflict" and conflict.value.status == 409
        again = mc.observe(sid, 26, walk[1].stimulus, "right", seq=1)
        assert again.replayed and again == b and not a.replayed
        assert mc.retries.total == 0  # refusals are never retried
        # The numbering goes on undisturbed.
        c = mc.observe(sid, 25, walk[2].stimulus, "left")
        assert c.tick == 2 and not c.replayed
        assert mc.get_session(sid).next_seq == 3


@pytest.mark.parametrize("kind", CLIENT_KINDS)
def test_another_writer_is_a_conflict_then_the_count_is_read_again(kind: str, server: Server) -> None:
    walk = _walk(3)
    with open_client(kind, server) as mc, Client(server.http_url) as other:
        sid = mc.create_session(WORLD, seed=13).id
        mc.observe(sid, 25)
        other.observe(sid, 26, walk[1].stimulus, "right")  # seq 1, read from next_seq
        with pytest.raises(SequenceRefused) as e:
            mc.observe(sid, 26, walk[1].stimulus, "stay")  # seq 1 again, other content
        assert e.value.code == "seq_conflict" and e.value.seq == 1
        step = mc.observe(sid, 25, walk[2].stimulus, "left")  # reads next_seq: 2
        assert step.tick == 2 and not step.replayed


def test_what_the_count_believes_after_a_failure() -> None:
    from mcapi_client.errors import TransportError as TE
    from mcapi_client.errors import error_for

    seqs = Sequences()
    seqs.learn("s", 0, force=True)
    assert seqs.take("s", 1) == (True, 0)
    seqs.answered("s", 0, 1)
    assert seqs.take("s", 1) == (True, 1)
    assert not seqs.failed("s", 1, 1, TE("x", code="transport_error"))
    assert seqs.next_seq("s") == 1  # taken again: a resend is replayed or applied once
    assert seqs.take("s", 1) == (True, 1)
    assert seqs.failed("s", 1, 1, error_for("seq_conflict", "x"))  # the lost one was applied
    assert seqs.take("s", 1) == (False, None)  # read the session again
    seqs.learn("s", 2)
    assert seqs.take("s", 3) == (True, 2)
    gap = error_for("seq_gap", "x")
    assert isinstance(gap, SequenceRefused)
    gap.expected_seq = 1
    seqs.failed("s", 2, 3, gap)
    assert seqs.next_seq("s") == 1  # goes on where the server is
    assert seqs.take("s", 2) == (True, 1)
    seqs.failed("s", 1, 2, error_for("unknown_state", "x"))  # a batch: some may be applied
    assert seqs.take("s", 1) == (False, None)
    seqs.learn("s", 4)
    assert seqs.take("s", 1) == (True, 4)
    seqs.failed("s", 4, 1, error_for("unknown_state", "x"))  # refused, nothing applied
    assert seqs.next_seq("s") == 4


def test_an_interact_stream_resumes_across_a_server_restart(tmp_path: Path) -> None:
    """The server stops (SIGTERM) with observations in flight and comes back
    on the same ports and data: the stream is reopened, the observations
    resent, each applied once."""
    if not re.search(r"^\s*-\s*redb\b", serve_help(), re.MULTILINE):
        pytest.skip("this mcapi binary has no durable store (--store redb)")
    walk = _walk(40)
    first = start_server(tmp_path)
    ports = (int(first.http_url.rsplit(":", 1)[1]), int(first.grpc_target.rsplit(":", 1)[1]))
    servers = [first]
    policy = RetryPolicy(deadline=30.0, initial_backoff=0.05, max_backoff=0.5)
    try:
        with GrpcClient(first.grpc_target, retry=policy) as mc:
            sid = mc.create_session(WORLD, seed=14).id
            with mc.interact(sid) as stream:
                steps = [stream.step(o.state, o.stimulus, o.action_taken) for o in walk[:20]]
                for o in walk[20:30]:
                    stream.send(o.state, o.stimulus, o.action_taken)
                first.stop()
                servers.append(start_server(tmp_path, ports=ports))
                steps += list(stream)
                steps += [stream.step(o.state, o.stimulus, o.action_taken) for o in walk[30:]]
            assert mc.retries.total >= 1, mc.retries
            info = mc.get_session(sid)
            assert (info.tick, info.next_seq) == (len(walk) - 1, len(walk))
        assert steps == _twin(servers[-1], walk, seed=14)
    finally:
        for s in servers:
            s.stop()


def test_interact_batch_steps_make_the_client_read_the_count_again(server: Server) -> None:
    """InteractBatch is unnumbered; the next numbered observe of a session
    it stepped reads next_seq, so it is neither a conflict nor a replay."""
    walk = _walk(3)
    with GrpcClient(server.grpc_target) as mc:
        sid = mc.create_session(WORLD, seed=15).id
        mc.observe(sid, 25)
        with mc.interact_batch() as stream:
            (result,) = stream.step([(sid, walk[1])])
        assert isinstance(result, Step) and result.tick == 1
        o = walk[2]
        step = mc.observe(sid, o.state, o.stimulus, o.action_taken)
        assert step.tick == 2 and not step.replayed
        assert mc.get_session(sid).next_seq == 3
