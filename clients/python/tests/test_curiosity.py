"""Sessions with a curiosity channel against the real server, over REST and
gRPC: the config, signal samples, xi_cur in steps and history, the channel's
state, errors, a module freezing."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from mcapi_client import (
    AsyncClient,
    Client,
    CuriosityConfig,
    GrpcClient,
    McapiError,
    Observation,
    models,
)

DT = 0.08  # the signal clock of the paper's Eq. 6 as the server's default `dt`
SITE = 25  # the hallway state where the book is


def book(t: float) -> list[float]:
    """The paper's Eq. 6 "book" signal at time t."""
    return [math.sin(t) + math.cos(11 * t) ** 2, math.cos(11 * t)]


def book_samples(start: int = 0) -> Iterator[list[float]]:
    """Book samples on the book's own clock, from sample ``start``."""
    n = start
    while True:
        yield book(n * DT)
        n += 1


def _create(mc: Client | GrpcClient, **kw: Any) -> str:
    return mc.create_session(models.hallway(), seed=5, curiosity=CuriosityConfig(2, {"gain": 800}), **kw).id


def _drive(mc: Client | GrpcClient, sid: str, n: int) -> list[Any]:
    """The first observation at SITE, then ``n`` book samples there, staying put."""
    steps = [mc.observe(sid, SITE)]
    samples = book_samples()
    for _ in range(n):
        steps.append(mc.observe(sid, SITE, [0.0, 0.0], "stay", signal=next(samples)))
    return steps


def test_create_returns_the_channel(client: Client, grpc_client: GrpcClient) -> None:
    for mc in (client, grpc_client):
        info = mc.create_session(
            models.hallway(), seed=2, priorities=[1.0, 1.0, 0.5],
            curiosity=CuriosityConfig(signal_dim=2, params={"gain": 400, "delta": 0.25}),
        )
        assert info.model.stimuli == ["food", "rest", "curiosity"]
        assert len(info.drive) == 3 and info.agent.priorities == [1.0, 1.0, 0.5]
        cfg = info.agent.curiosity
        assert cfg is not None and cfg.signal_dim == 2 and cfg.params is not None
        assert (cfg.params["gain"], cfg.params["delta"]) == (400, 0.25)
        assert {"tau", "lag", "clip", "dt", "freeze_after"} <= set(cfg.params), "every constant filled"
        assert info.curiosity is not None
        assert (info.curiosity.samples, info.curiosity.modules) == (0, [])
        assert mc.get_session(info.id) == info
        # The signal dimension alone takes every default.
        bare = mc.create_session("hallway", curiosity=2).agent.curiosity
        assert bare is not None and bare.params is not None and bare.params["gain"] == 800
    plain = client.create_session("hallway")
    assert plain.agent.curiosity is None and plain.curiosity is None
    assert grpc_client.get_session(plain.id).curiosity is None


@pytest.mark.parametrize("transport", ["rest", "grpc"])
def test_signal_samples_give_xi_cur_in_steps_history_and_state(
    transport: str, client: Client, grpc_client: GrpcClient
) -> None:
    mc: Client | GrpcClient = client if transport == "rest" else grpc_client
    sid = _create(mc, history=100)
    steps = _drive(mc, sid, 60)
    first = steps[0]
    assert first.curiosity is not None and first.curiosity.source is None
    assert first.curiosity.xi_cur == 0.0
    for s in steps[1:]:
        assert s.curiosity is not None and s.curiosity.source == 0 and s.curiosity.modules == 0
        assert len(s.drive) == 3
    xi = [s.curiosity.xi_cur for s in steps[1:] if s.curiosity is not None]
    assert max(xi) > 0, "a fresh module learning gives xi_cur > 0"
    assert all(0.0 <= x <= 12.0 for x in xi), "Eq. 7 clips to [0, 12]"
    # A tick without a signal: xi_cur 0, no source.
    quiet = mc.observe(sid, SITE, [0.0, 0.0], "stay")
    assert quiet.curiosity is not None and quiet.curiosity.xi_cur == 0.0 and quiet.curiosity.source is None
    steps.append(quiet)

    hist = mc.history(sid)  # the first observation makes no entry
    assert [h.tick for h in hist] == [s.tick for s in steps[1:]]
    for h, s in zip(hist, steps[1:]):
        assert h.curiosity == s.curiosity and h.drive == s.drive and h.action == s.action
        assert h.stimulus is not None and len(h.stimulus) == 3
        assert s.curiosity is not None and h.stimulus == [0.0, 0.0, s.curiosity.xi_cur]

    info = mc.get_session(sid)
    cur = info.curiosity
    assert cur is not None and cur.samples == 60 and cur.active_source == 0
    assert cur.active_samples == 60 and not cur.all_explained and cur.modules == []
    assert cur.epsilon == quiet.curiosity.epsilon
    values = mc.values(sid, "xi")
    assert values.curiosity == cur
    assert values.xi is not None and len(values.xi[SITE][2] or []) == 3


def test_rest_and_grpc_agree(client: Client, grpc_client: GrpcClient) -> None:
    rest_id, grpc_id = _create(client, history=300), _create(grpc_client, history=300)
    assert client.get_session(rest_id).agent == grpc_client.get_session(grpc_id).agent
    a, b = _drive(client, rest_id, 40), _drive(grpc_client, grpc_id, 40)
    assert a == b
    samples = book_samples(40)
    batch = [
        Observation(SITE, [0.0, 0.0], "stay", signal=next(samples), signal_source=0) for _ in range(100)
    ]
    assert client.observe_batch(rest_id, batch) == grpc_client.observe_batch(grpc_id, batch)
    with grpc_client.interact(grpc_id) as stream:
        for _ in range(20):
            x = next(samples)
            assert stream.step(SITE, [0.0, 0.0], "stay", signal=x) == client.observe(
                rest_id, SITE, [0.0, 0.0], "stay", signal=x
            )
    assert client.history(rest_id) == grpc_client.history(grpc_id)
    assert client.history(rest_id, limit=3) == grpc_client.history(grpc_id, limit=3)
    r, g = client.get_session(rest_id), grpc_client.get_session(grpc_id)
    assert (r.curiosity, r.drive, r.tick) == (g.curiosity, g.drive, g.tick)
    assert client.values(rest_id, "all") == grpc_client.values(grpc_id, "all")
    # A fresh gRPC client (nothing cached) names the history's actions too.
    with GrpcClient(grpc_client.target) as fresh:
        assert fresh.history(grpc_id, limit=5) == client.history(rest_id, limit=5)


def _same_error(rest_call: Callable[[], object], grpc_call: Callable[[], object]) -> McapiError:
    with pytest.raises(McapiError) as r:
        rest_call()
    with pytest.raises(McapiError) as g:
        grpc_call()
    assert type(r.value) is type(g.value) and r.value.code == g.value.code
    assert r.value.status == 400 and g.value.grpc_code == "INVALID_ARGUMENT"
    return r.value


def test_signal_errors(client: Client, grpc_client: GrpcClient) -> None:
    plain_r, plain_g = client.create_session("hallway").id, grpc_client.create_session("hallway").id
    client.observe(plain_r, SITE)
    grpc_client.observe(plain_g, SITE)
    err = _same_error(
        lambda: client.observe(plain_r, SITE, [0.0, 0.0], "stay", signal=[1.0, 0.0]),
        lambda: grpc_client.observe(plain_g, SITE, [0.0, 0.0], "stay", signal=[1.0, 0.0]),
    )
    assert "signal" in str(err)

    cur_r, cur_g = _create(client), _create(grpc_client)
    _same_error(  # a signal on the first observation
        lambda: client.observe(cur_r, SITE, signal=[1.0, 0.0]),
        lambda: grpc_client.observe(cur_g, SITE, signal=[1.0, 0.0]),
    )
    client.observe(cur_r, SITE)
    grpc_client.observe(cur_g, SITE)
    _same_error(  # the full stimulus, curiosity included: the server appends it
        lambda: client.observe(cur_r, SITE, [0.0, 0.0, 0.0], "stay", signal=[1.0, 0.0]),
        lambda: grpc_client.observe(cur_g, SITE, [0.0, 0.0, 0.0], "stay", signal=[1.0, 0.0]),
    )
    _same_error(  # a signal of the wrong dimension
        lambda: client.observe(cur_r, SITE, [0.0, 0.0], "stay", signal=[1.0, 0.0, 2.0]),
        lambda: grpc_client.observe(cur_g, SITE, [0.0, 0.0], "stay", signal=[1.0, 0.0, 2.0]),
    )
    _same_error(  # a source without a signal
        lambda: client.observe(cur_r, SITE, [0.0, 0.0], "stay", signal_source=1),
        lambda: grpc_client.observe(cur_g, SITE, [0.0, 0.0], "stay", signal_source=1),
    )
    # None of these ticked.
    assert client.get_session(cur_r).tick == grpc_client.get_session(cur_g).tick == 0


def test_a_module_freezes_and_explains_its_source(client: Client, grpc_client: GrpcClient) -> None:
    """About 1-3k book samples: the active module's error falls below delta,
    it freezes, and the book is explained (later samples give xi_cur 0)."""
    sid = _create(client, history=10)
    client.observe(sid, SITE)
    samples = book_samples()
    frozen_at = None
    for _ in range(6):
        batch = [Observation(SITE, [0.0, 0.0], "stay", signal=next(samples)) for _ in range(500)]
        steps = client.observe_batch(sid, batch)
        frozen = [s for s in steps if s.curiosity is not None and s.curiosity.modules == 1]
        if frozen:
            frozen_at = frozen[0].tick
            break
    assert frozen_at is not None, f"no module froze: {client.get_session(sid).curiosity}"
    cur = client.get_session(sid).curiosity
    assert cur is not None and len(cur.modules) == 1
    module = cur.modules[0]
    assert (module.source, module.frozen_tick) == (0, frozen_at)
    assert 100 <= module.learned_samples <= frozen_at
    assert cur.all_explained and cur.active_source is None
    after = client.observe(sid, SITE, [0.0, 0.0], "stay", signal=next(samples))
    assert after.curiosity is not None and after.curiosity.xi_cur == 0.0, "an explained sample"
    assert after.drive[2] == 0.0, "D[curiosity] is held at 0 while every source is explained"
    assert grpc_client.get_session(sid).curiosity == client.get_session(sid).curiosity


@pytest.mark.anyio
async def test_async_client_sends_signals(server: Any) -> None:
    async with AsyncClient(server.http_url) as mc:
        info = await mc.create_session("hallway", seed=3, curiosity={"signal_dim": 2})
        await mc.observe(info.id, SITE)
        step = await mc.observe(info.id, SITE, [0.0, 0.0], "stay", signal=book(0.0), signal_source=0)
        assert step.curiosity is not None and step.curiosity.source == 0
        steps = await mc.observe_batch(
            info.id, [{"state": SITE, "stimulus": [0.0, 0.0], "action_taken": "stay", "signal": book(DT)}]
        )
        hist = await mc.history(info.id)
        assert hist[-1].curiosity == steps[0].curiosity and hist[-2].curiosity == step.curiosity
        got = await mc.get_session(info.id)
        assert got.curiosity is not None and got.curiosity.samples == 2
