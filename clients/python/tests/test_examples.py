"""The examples' main functions on short runs against the real server."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest
from conftest import Server


def _run(module: str, argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    example = importlib.import_module(module)
    assert example.main(argv) == 0
    return capsys.readouterr().out


def test_hallway_rest(
    server: Server, examples_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plot = tmp_path / "drive.png"
    out = _run("hallway_rest", ["--url", server.http_url, "--steps", "400", "--plot", str(plot)], capsys)
    switches = re.findall(r"tick +\d+: seeking (food|rest)", out)
    assert len(switches) >= 3, out  # the start, then at least two switches
    visits = dict(re.findall(r"(food|rest) (\d+)", out.splitlines()[-2 if "plot" in out else -1]))
    assert int(visits["food"]) > 0 and int(visits["rest"]) > 0, out
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        assert "matplotlib is not installed" in out
    else:
        assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", "a PNG was saved"
        assert f"saved the plot of D over time to {plot}" in out


def test_hallway_stream(server: Server, examples_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = _run(
        "hallway_stream",
        ["--target", server.grpc_target, "--steps", "2000", "--report-every", "0.2"],
        capsys,
    )
    final = re.search(
        r"2000 ticks in [\d.]+ s: (\d+) ticks/s; (\d+) drive switches; visits: food (\d+), rest (\d+)",
        out,
    )
    assert final, out
    rate, switches, food, rest = map(int, final.groups())
    assert rate > 0 and switches >= 10 and food > 0 and rest > 0, out
    assert re.search(r"^ +\d+ ticks/s$", out, re.MULTILINE), "rate lines while running"


@pytest.mark.parametrize(
    "args",
    [["--in-flight", "2"], ["--in-flight", "3"], ["--in-flight", "1"], ["--transport", "rest"]],
)
def test_hallway_group(
    args: list[str], server: Server, examples_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("numpy", reason="the vector extra is not installed")
    from mcapi_client import Client

    with Client(server.http_url) as c:
        before = {s.id for s in c.iter_sessions()}
    common = ["--target", server.grpc_target, "--url", server.http_url, "--agents", "64", "--steps", "300"]
    out = _run("hallway_group", [*common, "--report-every", "0.1", *args], capsys)
    final = re.search(
        r"64 agents x 300 steps in [\d.]+ s: (\d+) agent steps/s, (\d+) group steps/s; "
        r"visits: food (\d+), rest (\d+)",
        out,
    )
    assert final, out
    rate, group_rate, food, rest = map(int, final.groups())
    assert rate > group_rate > 0 and food > 64 and rest > 64, out
    with Client(server.http_url) as c:
        assert {s.id for s in c.iter_sessions()} == before, "the group was deleted"


def test_frozenlake(server: Server, examples_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("gymnasium", reason="the gymnasium extra is not installed")
    out = _run("frozenlake", ["--url", server.http_url, "--steps", "1500", "--window", "500"], capsys)
    assert "FrozenLake 4x4, slippery: 16 states" in out
    assert len(re.findall(r"^ticks +\d+: visits", out, re.MULTILINE)) == 3
    total = re.search(r"total visits: food (\d+), water (\d+)", out)
    assert total, out
    food, water = map(int, total.groups())
    assert food > 0 and water > 0, "the agent reaches both sources"
    assert min(food, water) >= 0.3 * max(food, water), f"balanced: food {food}, water {water}"


def test_examples_delete_their_sessions(
    server: Server, examples_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from mcapi_client import Client

    with Client(server.http_url) as c:
        before = {s.id for s in c.iter_sessions()}
        _run("hallway_rest", ["--url", server.http_url, "--steps", "5", "--no-plot"], capsys)
        _run("hallway_rest", ["--url", server.http_url, "--steps", "5", "--no-plot", "--keep"], capsys)
        after = {s.id for s in c.iter_sessions()}
    assert len(after - before) == 1, "only the --keep run left its session"


def test_curiosity(server: Server, examples_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = _run("curiosity", ["--url", server.http_url, "--steps", "2000"], capsys)
    assert "stimuli food, rest, curiosity; book at 25" in out
    froze = re.findall(
        r"^tick +\d+: a module froze after learning source 0 from (\d+) book samples", out, re.MULTILINE
    )
    assert len(froze) == 1 and int(froze[0]) >= 100, out
    summary = re.search(r"2000 ticks: (\d+) book samples, 1 frozen module\(s\), the book explained", out)
    assert summary and int(summary.group(1)) >= int(froze[0]), out
    visits = re.search(r"visits: food (\d+), rest (\d+), book (\d+)", out)
    assert visits and all(int(v) > 0 for v in visits.groups()), out


def test_learned_maze(server: Server, examples_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = _run(
        "learned_maze",
        ["--url", server.http_url, "--steps", "3000", "--known-after", "1", "--report-every", "1000"],
        capsys,
    )
    known = [float(x) for x in re.findall(r"tick +\d+: ([0-9.]+) of the model known", out)]
    assert len(known) == 3 and known == sorted(known) and known[-1] > 0.5, out
    assert len(re.findall(r"first reached source [abc]", out)) == 3, out
    visits = dict(re.findall(r"([abc]) (\d+)", out.splitlines()[-1]))
    assert all(int(visits[s]) > 0 for s in "abc"), out


def test_mo_resource_gathering(
    server: Server, examples_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("mo_gymnasium", reason="the mo extra is not installed")
    out = _run(
        "mo_resource_gathering",
        ["--url", server.http_url, "--steps", "2000", "--report-every", "1000"],
        capsys,
    )
    head = "100 states, actions up, down, left, right; stimuli gold, gem; penalties left out: enemy"
    assert head in out, out
    known = [float(x) for x in re.findall(r"tick +\d+: ([0-9.]+) of the model known", out)]
    assert len(known) == 2 and known[-1] > 0.85, out
    final = re.search(
        r"2000 ticks, (\d+) episodes: per objective enemy ([-+]\d+), gold \+(\d+), gem \+(\d+); "
        r"balance \(fewer/more\) ([0-9.]+)",
        out,
    )
    assert final, out
    episodes, enemy, gold, gem = map(int, final.groups()[:4])
    assert episodes > 50 and enemy <= 0, out
    assert gold >= 30 and gem >= 30, f"both resources brought home often: {out}"
    assert float(final.group(5)) >= 0.8, out


def test_minecart(server: Server, examples_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("mo_gymnasium", reason="the mo extra is not installed")
    out = _run("minecart", ["--url", server.http_url, "--steps", "1000", "--seeds", "1"], capsys)
    found = re.findall(
        r"(agent|random)\s*: ore1 ([0-9.]+), ore2 ([0-9.]+) per run of 1000 ticks", out
    )
    rows = {name: (float(a), float(b)) for name, a, b in found}
    assert set(rows) == {"agent", "random"}, out
    per_seed = re.search(
        r"seed 1: agent ore1 ([0-9.]+), ore2 ([0-9.]+); random ore1 ([0-9.]+), ore2 ([0-9.]+)", out
    )
    assert per_seed, out
    assert (float(per_seed.group(1)), float(per_seed.group(2))) == rows["agent"], out
    # The random run is the environment's alone: the same seed, the same ore.
    again = _run("minecart", ["--url", server.http_url, "--steps", "1000", "--seeds", "1"], capsys)
    assert again == out, "runs are reproducible (minecart's mines draw from numpy's seeded generator)"
    assert sum(rows["agent"]) > 0, f"the agent delivers ore: {out}"


def test_continuous_point(server: Server, examples_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = _run(
        "continuous_point", ["--url", server.http_url, "--steps", "600", "--report-every", "300"], capsys
    )
    # The default for d = 2: the grid planner.
    assert "point world: [0, 1]^2, 4 moves, sources food, water, rest; basis {'kind': 'grid'" in out, out
    assert len(re.findall(r"^tick +\d+: seeking (food|water|rest); arrivals", out, re.MULTILINE)) == 2, out
    agent = re.search(
        r"agent : 600 ticks, arrivals food (\d+), water (\d+), rest (\d+); balance ([0-9.]+)", out
    )
    walk = re.search(r"random: 600 ticks, arrivals food (\d+), water (\d+), rest (\d+)", out)
    assert agent and walk, out
    assert sum(map(int, agent.groups()[:3])) >= 1, f"the agent reaches a source: {out}"
    held = re.search(
        r"^grid: (\d+) moves kept, (\d+) \(cell, action\) pairs known; 0 observations clipped$",
        out,
        re.MULTILINE,
    )
    # A move teaches every cell within reach; at most 4 actions × 64² pairs.
    assert held and int(held.group(1)) > 600 and 0 < int(held.group(2)) <= 4 * 64 * 64, out


def test_examples_say_in_one_line_what_went_wrong(tmp_path: Path, examples_path: Path) -> None:
    """A missing API key or an unreachable server is one line on stderr and
    exit status 1, not a traceback."""
    import subprocess
    import sys

    from conftest import start_server

    keyed = start_server(tmp_path, ["--api-key", "examples-key-0123456789"])
    try:
        for url, line in (
            (keyed.http_url, "mcapi: this server needs an API key: --api-key or MCAPI_API_KEY"),
            ("http://127.0.0.1:9", "mcapi: cannot reach the server"),
        ):
            done = subprocess.run(
                [sys.executable, str(examples_path / "hallway_rest.py"), "--url", url, "--no-plot"],
                capture_output=True,
                text=True,
                timeout=60,
                env={"PATH": "/usr/bin:/bin"},
            )
            assert done.returncode == 1, done
            assert done.stderr.startswith(line) and "Traceback" not in done.stderr, done.stderr
        done = subprocess.run(
            [sys.executable, str(examples_path / "continuous_point.py"), "--url", "http://127.0.0.1:9"],
            capture_output=True,
            text=True,
            timeout=60,
            env={"PATH": "/usr/bin:/bin"},
        )
        assert done.returncode == 1 and done.stderr.startswith("mcapi: cannot reach the server"), done
    finally:
        keyed.stop()
