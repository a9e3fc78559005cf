"""Exactly-once group steps: the group clients number each member's
observation (the ``seqs`` column) and a step resent after a lost answer is
replayed by the members that applied it, over REST (the client resends it
itself) and gRPC (the next stream of the same client sends it again); the
per-member counts after each kind of refusal, without a server."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from conftest import Server
from test_delivery import FAST, CutProxy, _via

from mcapi_client import Client, GrpcClient, McapiError, models
from mcapi_client.groups import GroupSeqs, GroupStep, MemberStatus

WORLD = models.hallway()
ZEROS = np.zeros((3, 2))


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


def test_a_rest_step_whose_answer_was_lost_is_resent_and_replayed(
    server: Server, http_proxy: CutProxy
) -> None:
    with Client(_via(server, http=http_proxy).http_url, retry=FAST) as mc:
        agents = mc.create_group(WORLD, 3, seed=5, update_mode="lockstep")
        first = agents.step([25, 25, 25])
        assert first.replayed.tolist() == [False] * 3
        applied = agents.step([24, 26, 25], ZEROS)
        http_proxy.cut(1)
        again = agents.step([23, 27, 25], ZEROS)
        assert http_proxy.cut_done == 1 and mc.retries["transport_error"] == 1
        # Applied once by the request whose answer was lost, replayed by the resend.
        assert again.replayed.tolist() == [True] * 3 and again.ticks.tolist() == [2, 2, 2]
        assert [mc.get_session(m).tick for m in agents.info.members] == [2, 2, 2]
        after = agents.step([22, 28, 25], ZEROS)
        assert after.replayed.tolist() == [False] * 3 and after.ticks.tolist() == [3, 3, 3]
        assert applied.ticks.tolist() == [1, 1, 1]
        mc.delete_group(agents.info.id)


def test_a_broken_step_group_stream_is_resent_by_the_next_one(
    server: Server, grpc_proxy: CutProxy
) -> None:
    with GrpcClient(_via(server, grpc=grpc_proxy).grpc_target, retry=FAST) as mc:
        with mc.create_group(WORLD, 3, seed=6, update_mode="lockstep") as agents:
            gid = agents.info.id
            agents.step([25, 25, 25])
            applied = agents.step([24, 26, 25], ZEROS)
            # The reply of the next step (more than 30 bytes) is cut after
            # the server applied it: the stream breaks.
            grpc_proxy.cut(1, min_bytes=30)
            agents.send([23, 27, 25], ZEROS)
            with pytest.raises(McapiError):
                agents.recv()
        assert grpc_proxy.cut_done == 1
        with mc.vector_agents(gid) as agents:
            again = agents.step([23, 27, 25], ZEROS)
            assert again.replayed.tolist() == [True] * 3, again
            assert again.ticks.tolist() == [2, 2, 2] and not again.errors
            after = agents.step([22, 28, 25], ZEROS)
            assert after.replayed.tolist() == [False] * 3 and after.ticks.tolist() == [3, 3, 3]
        assert applied.ticks.tolist() == [1, 1, 1]
        mc.delete_group(gid)


def test_another_writer_is_a_member_conflict_and_the_count_is_learned_again(
    client: Client, server: Server
) -> None:
    agents = client.create_group(WORLD, 3, seed=7)
    info = agents.info
    agents.step([25, 25, 25])
    # Member 1 observed elsewhere, unnumbered: the group's seq 1 for it is taken.
    with Client(server.http_url, exactly_once=False) as other:
        other.observe(info.members[1], 20, [0.0, 0.0])
    clash = agents.step([24, 26, 25], ZEROS)
    assert [(e.index, e.code) for e in clash.errors] == [(1, "seq_conflict")]
    assert clash.ticks.tolist() == [1, 0, 1]
    # Its count is unknown: the next step goes unnumbered and learns it.
    counts = client._protocol.group_seqs(info)
    assert counts is not None and counts.next_seqs().tolist() == [2, -1, 2]
    plain = agents.step([23, 27, 25], ZEROS)
    assert not plain.errors and plain.ticks.tolist() == [2, 2, 2]
    assert counts.next_seqs().tolist() == [3, 3, 3]
    numbered = agents.step([22, 28, 25], ZEROS)
    assert not numbered.errors and numbered.ticks.tolist() == [3, 3, 3]
    # A client that did not create the group learns every count from its first step.
    with Client(server.http_url) as fresh:
        attached = fresh.vector_agents(info.id)
        step = attached.step([21, 29, 25], ZEROS)
        assert step.ticks.tolist() == [4, 4, 4]
        got = fresh._protocol.group_seqs(info)
        assert got is not None and got.next_seqs().tolist() == [5, 5, 5]
        assert attached.step([20, 30, 25], ZEROS).ticks.tolist() == [5, 5, 5]
    client.delete_group(info.id)


def _reply(ticks: list[int], errors: list[MemberStatus] | None = None) -> GroupStep:
    m = len(ticks)
    return GroupStep(
        seq=0,
        actions=np.zeros(m, dtype=np.uint32),
        drives=np.zeros((m, 2)),
        rewards=np.zeros(m),
        policy_versions=np.zeros(m, dtype=np.uint64),
        ticks=np.asarray(ticks, dtype=np.uint64),
        errors=errors or [],
    )


def test_what_the_member_counts_believe_after_each_answer() -> None:
    every = np.arange(4, dtype=np.intp)
    seqs = GroupSeqs(4, known=True)
    sent = seqs.take(every)
    assert sent is not None and sent.tolist() == [0, 0, 0, 0]
    second = seqs.take(np.array([1, 3], dtype=np.intp))  # pipelined
    assert second is not None and second.tolist() == [1, 1]
    seqs.answered(every, sent, _reply([0, 0, 0, 0]))
    # A refusal that applied nothing gives the seq back only if no later
    # step took the next one; a gap resumes from the server's count; a
    # conflict forgets the count.
    seqs.answered(
        np.array([1, 3], dtype=np.intp),
        second,
        _reply([0, 0], [MemberStatus(1, "unknown_action", ""), MemberStatus(3, "seq_gap", "", 7)]),
    )
    assert seqs.next_seqs().tolist() == [1, 1, 1, 7]
    third = seqs.take(every)
    assert third is not None and third.tolist() == [1, 1, 1, 7]
    seqs.answered(every, third, _reply([1, 0, 1, 0], [MemberStatus(1, "seq_conflict", "")]))
    assert seqs.next_seqs().tolist() == [2, -1, 2, 8]
    # Unknown: unnumbered, learned from the ticks; not numbered while an
    # unnumbered step of the member is in flight.
    assert seqs.take(every) is None
    assert seqs.take(np.array([0], dtype=np.intp)) is None
    seqs.answered(every, None, _reply([2, 5, 2, 8]))
    seqs.answered(np.array([0], dtype=np.intp), None, _reply([3]))
    assert seqs.next_seqs().tolist() == [4, 6, 3, 9]
    # Steps without an answer give their seqs back, newest first.
    a = seqs.take(every)
    b = seqs.take(np.array([2], dtype=np.intp))
    assert a is not None and b is not None and b.tolist() == [4]
    seqs.failed(np.array([2], dtype=np.intp), b)
    seqs.failed(every, a)
    assert seqs.next_seqs().tolist() == [4, 6, 3, 9]
