#!/usr/bin/env python3
"""Runs the README's commands as pasted, in order, in one fresh shell.

Every fenced ``sh`` and ``python`` block of README.md runs in one bash
session from the repository root, as a user pasting them into one terminal
would (a ``python`` block as ``python3 -`` in that shell, so a venv the
README activated is the one used), against an ``mcapi serve`` this harness
starts first (the README's "start the server" step; its ``--data-dir`` is a
temporary directory). ``mcapi`` is the binary under test (``MCAPI_BIN``,
default target/debug/mcapi), first on PATH.

A block fails the run when a command in it exits non-zero (``set -e``), or
when the output the README shows is not what it printed. Shown output is a
comment line in the block that starts with ``# {``, ``# [`` or ``# → ``:
the block's output must contain those lines in that order (other lines may
come between). In a shown line ``...`` stands for any text, and session ids
(``s0123.01ARZ...``) are masked on both sides.

A block is skipped when the line before its fence is
``<!-- readme-test: skip (why) -->``; ``<!-- readme-test: needs TOOL -->``
runs it only when TOOL is on PATH (and says so when it is not).

Usage: python3 tools/readme_test.py [README.md]
"""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ID = re.compile(r"s[0-9a-f]{4}\.[0-9A-HJKMNP-TV-Z]{26}")

MARK = "@@readme-test block {}@@"


@dataclass
class Block:
    """One fenced block: where it starts, its language, its text."""

    line: int
    lang: str
    text: str
    skip: str | None = None
    needs: str | None = None
    shown: list[str] = field(default_factory=list)


def blocks(markdown: str) -> list[Block]:
    """The ``sh`` and ``python`` blocks, with their directives and shown output."""
    out: list[Block] = []
    lines = markdown.splitlines()
    i = 0
    while i < len(lines):
        m = re.match(r"^```(\w+)\s*$", lines[i])
        if not m:
            i += 1
            continue
        start = i
        j = i + 1
        while j < len(lines) and not lines[j].startswith("```"):
            j += 1
        lang = m.group(1)
        if lang in ("sh", "python"):
            b = Block(start + 1, lang, "\n".join(lines[start + 1 : j]) + "\n")
            before = lines[start - 1] if start > 0 else ""
            d = re.match(r"^<!-- readme-test: (skip|needs) (.*?) -->$", before)
            if d and d.group(1) == "skip":
                b.skip = d.group(2)
            elif d:
                b.needs = d.group(2)
            for raw in b.text.splitlines():
                s = raw.strip()
                if s.startswith("# → "):
                    b.shown.append(s[len("# → ") :])
                elif s.startswith("# {") or s.startswith("# ["):
                    b.shown.append(s[2:])
            out.append(b)
        i = j + 1
    return out


def pattern(shown: str) -> re.Pattern[str]:
    """A shown line as a regular expression: `...` is any text, ids masked."""
    text = ID.sub("ID", shown)
    return re.compile(".*".join(re.escape(part) for part in text.split("...")))


def free(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) != 0


def wait_ready(url: str, proc: subprocess.Popen[bytes], log: Path) -> None:
    import urllib.request

    deadline = time.time() + 30
    while time.time() < deadline:
        if proc.poll() is not None:
            sys.exit(f"readme-test: mcapi serve exited:\n{log.read_text()}")
        try:
            with urllib.request.urlopen(url, timeout=1) as r:
                if r.status == 200:
                    return
        except OSError:
            time.sleep(0.1)
    sys.exit(f"readme-test: mcapi serve not ready after 30 s:\n{log.read_text()}")


def main() -> int:
    readme = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "README.md"
    binary = Path(os.environ.get("MCAPI_BIN", ROOT / "target/debug/mcapi")).resolve()
    if not binary.is_file():
        sys.exit(f"readme-test: {binary} is missing (cargo build first)")
    for port in (8080, 50051):
        if not free(port):
            sys.exit(f"readme-test: port {port} is taken; the README's commands use it")
    found = blocks(readme.read_text())
    work = Path(tempfile.mkdtemp(prefix="readme-test-"))
    bindir = work / "bin"
    bindir.mkdir()
    (bindir / "mcapi").symlink_to(binary)
    env = {k: v for k, v in os.environ.items() if not k.startswith("MCAPI_") and k != "VIRTUAL_ENV"}
    env["PATH"] = f"{bindir}:{env.get('PATH', '')}"
    log = work / "serve.log"
    with log.open("wb") as out:
        server = subprocess.Popen(
            [str(binary), "serve", "--data-dir", str(work / "data")],
            cwd=work,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    script = ["set -euo pipefail"]
    ran: list[Block] = []
    try:
        wait_ready("http://127.0.0.1:8080/readyz", server, log)
        for n, b in enumerate(found):
            if b.skip:
                print(f"README.md:{b.line}: skipped {b.skip}")
                continue
            if b.needs and shutil.which(b.needs, path=env["PATH"]) is None:
                print(f"README.md:{b.line}: not run: `{b.needs}` is not installed")
                continue
            # On a line of its own, whatever the block before left unended.
            script.append(f"printf '\\n%s %s\\n' '{MARK.format(n)}' \"$(date +%s.%N)\"")
            if b.lang == "python":
                script.append(f"python3 - <<'README_PYTHON_{n}'\n{b.text}README_PYTHON_{n}")
            else:
                script.append(b.text)
            ran.append(b)
        script.append(f"printf '\\n%s %s\\n' '{MARK.format('end')}' \"$(date +%s.%N)\"")
        started = time.time()
        proc = subprocess.run(
            ["bash", "-c", "\n".join(script)],
            cwd=ROOT,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            timeout=900,
        )
        elapsed = time.time() - started
    finally:
        server.terminate()
        try:
            server.wait(timeout=15)
        except subprocess.TimeoutExpired:
            server.kill()
    output = proc.stdout
    # The output of each block, by its marker.
    chunks: dict[int, list[str]] = {}
    started_at: dict[int, float] = {}
    took: dict[int, float] = {}
    current: int | None = None
    ended = False
    for line in output.splitlines():
        m = re.fullmatch(r"@@readme-test block (\d+|end)@@ ([0-9.]+)", line)
        if m:
            at = float(m.group(2))
            if current is not None:
                took[current] = at - started_at[current]
            ended = m.group(1) == "end"
            current = None if ended else int(m.group(1))
            if current is not None:
                started_at[current] = at
            chunks.setdefault(current if current is not None else -1, [])
            continue
        if current is not None:
            chunks[current].append(line)
    problems = []
    for b in ran:
        n = found.index(b)
        got = chunks.get(n)
        if got is None:
            continue
        at = 0
        for shown in b.shown:
            rx = pattern(shown)
            while at < len(got) and not rx.fullmatch(ID.sub("ID", got[at])):
                at += 1
            if at == len(got):
                problems.append(
                    f"README.md:{b.line}: the README shows\n    {shown}\n  but the block printed:\n"
                    + "\n".join("    " + g for g in chunks[n][-20:])
                )
                break
            at += 1
    if proc.returncode != 0 or not ended:
        last = max((k for k in chunks if k >= 0), default=None)
        where = f"README.md:{found[last].line}" if last is not None else "README.md"
        problems.append(
            f"{where}: a command failed (exit {proc.returncode}); its output:\n"
            + "\n".join("    " + g for g in (chunks.get(last) or output.splitlines())[-30:])
        )
    for b in ran:
        n = found.index(b)
        secs = f"{took[n]:.1f} s" if n in took else "did not finish"
        print(f"README.md:{b.line}: {b.lang} block run in {secs}, {len(b.shown)} shown line(s) checked")
    if problems:
        print("\n".join(problems), file=sys.stderr)
        print(f"readme-test: {len(problems)} problem(s); server log: {log}", file=sys.stderr)
        return 1
    print(f"readme-test: {len(ran)} blocks ran as pasted in {elapsed:.1f} s")
    shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
