#!/usr/bin/env python3
"""Generates the gRPC stubs of mcapi_client from the repository's proto/.

    python tools/gen_stubs.py            # rewrite mcapi_client/_proto/
    python tools/gen_stubs.py --check    # exit 1 if the committed stubs are stale

Runs grpcio-tools' protoc (``--python_out``, ``--pyi_out``,
``--grpc_python_out``), then makes the output importable from inside the
package: the generated ``from mcapi.v1 import ...`` lines become
``from mcapi_client._proto.mcapi.v1 import ...``, and every package folder gets
an ``__init__.py``. The output depends only on the protos and the
grpcio-tools version, which is recorded in ``_proto/__init__.py``; the test
``tests/test_stubs.py`` regenerates into a temporary folder and compares.
"""

from __future__ import annotations

import argparse
import filecmp
import re
import subprocess
import sys
import tempfile
from importlib import metadata
from pathlib import Path

HERE = Path(__file__).resolve().parent
PACKAGE_ROOT = HERE.parent
REPO_ROOT = PACKAGE_ROOT.parent.parent
PROTO_ROOT = REPO_ROOT / "proto"
STUBS_DIR = PACKAGE_ROOT / "mcapi_client" / "_proto"
IMPORT_PREFIX = "mcapi_client._proto"

INIT_DOC = '''"""Generated gRPC stubs of proto/{package} (tools/gen_stubs.py; do not edit)."""
'''

ROOT_INIT = '''"""Generated gRPC stubs of the mcapi protos (tools/gen_stubs.py; do not edit).

Regenerate with ``python clients/python/tools/gen_stubs.py`` after changing
``proto/``; ``tests/test_stubs.py`` fails while they differ.
"""

GRPCIO_TOOLS_VERSION = "{version}"
"""The grpcio-tools version that generated these stubs."""
'''


def proto_files(proto_root: Path = PROTO_ROOT) -> list[Path]:
    """The .proto files under ``proto_root``, relative to it, sorted."""
    return sorted(p.relative_to(proto_root) for p in proto_root.rglob("*.proto"))


def _fix_imports(text: str, packages: set[str]) -> str:
    """Rewrites imports of the generated modules to go through the package."""
    for pkg in sorted(packages):
        text = re.sub(
            rf"^(\s*)from {re.escape(pkg)} import ",
            rf"\1from {IMPORT_PREFIX}.{pkg} import ",
            text,
            flags=re.MULTILINE,
        )
        text = re.sub(
            rf"^(\s*)import {re.escape(pkg)}\.",
            rf"\1import {IMPORT_PREFIX}.{pkg}.",
            text,
            flags=re.MULTILINE,
        )
    return text


def generate(out_dir: Path, proto_root: Path = PROTO_ROOT) -> list[Path]:
    """Generates the stubs into ``out_dir`` (created); returns the files written."""
    import grpc_tools  # noqa: PLC0415 - a test-time dependency only

    out_dir.mkdir(parents=True, exist_ok=True)
    protos = proto_files(proto_root)
    if not protos:
        raise SystemExit(f"no .proto files under {proto_root}")
    well_known = Path(grpc_tools.__file__).parent / "_proto"
    cmd = [
        sys.executable,
        "-m",
        "grpc_tools.protoc",
        f"-I{proto_root}",
        f"-I{well_known}",
        f"--python_out={out_dir}",
        f"--pyi_out={out_dir}",
        f"--grpc_python_out={out_dir}",
        *(str(p) for p in protos),
    ]
    subprocess.run(cmd, check=True)
    packages = {".".join(p.parent.parts) for p in protos}
    written: list[Path] = []
    for path in sorted(out_dir.rglob("*")):
        if path.suffix in (".py", ".pyi"):
            path.write_text(_fix_imports(path.read_text(), packages))
            written.append(path)
    # Package folders: every directory from out_dir down to each proto's.
    dirs = {out_dir}
    for p in protos:
        for i in range(1, len(p.parent.parts) + 1):
            dirs.add(out_dir.joinpath(*p.parent.parts[:i]))
    for d in sorted(dirs):
        init = d / "__init__.py"
        if d == out_dir:
            init.write_text(ROOT_INIT.format(version=metadata.version("grpcio-tools")))
        else:
            init.write_text(INIT_DOC.format(package="/".join(d.relative_to(out_dir).parts)))
        written.append(init)
    return sorted(written)


def differences(expected: Path, actual: Path) -> list[str]:
    """Files that differ, or exist on one side only, between two stub trees."""

    def files(root: Path) -> set[Path]:
        return {
            p.relative_to(root)
            for p in root.rglob("*")
            if p.is_file() and "__pycache__" not in p.parts
        }

    a, b = files(expected), files(actual)
    out = [f"only in {expected}: {p}" for p in sorted(a - b)]
    out += [f"only in {actual}: {p}" for p in sorted(b - a)]
    out += [
        f"differs: {p}"
        for p in sorted(a & b)
        if not filecmp.cmp(expected / p, actual / p, shallow=False)
    ]
    return out


def main(argv: list[str] | None = None) -> int:
    """Command line: regenerate, or ``--check`` the committed stubs."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="compare instead of writing")
    parser.add_argument("--out", type=Path, default=STUBS_DIR, help="output folder")
    args = parser.parse_args(argv)
    if args.check:
        with tempfile.TemporaryDirectory() as tmp:
            generate(Path(tmp))
            diff = differences(args.out, Path(tmp))
        for line in diff:
            print(line)
        return 1 if diff else 0
    # Stale stubs of removed protos go; nothing else in the folder is touched.
    for pattern in ("*_pb2.py", "*_pb2.pyi", "*_pb2_grpc.py"):
        for stale in args.out.rglob(pattern):
            stale.unlink()
    for path in generate(args.out):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
