"""The committed gRPC stubs are exactly what tools/gen_stubs.py makes of proto/."""

from __future__ import annotations

import importlib.util
from importlib import metadata
from pathlib import Path
from types import ModuleType

from conftest import PACKAGE_ROOT


def _gen_stubs() -> ModuleType:
    spec = importlib.util.spec_from_file_location("gen_stubs", PACKAGE_ROOT / "tools" / "gen_stubs.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_committed_stubs_match_a_fresh_generation(tmp_path: Path) -> None:
    gen = _gen_stubs()
    committed = PACKAGE_ROOT / "mcapi_client" / "_proto"
    recorded = (committed / "__init__.py").read_text()
    installed = metadata.version("grpcio-tools")
    assert f'GRPCIO_TOOLS_VERSION = "{installed}"' in recorded, (
        f"the stubs were not generated with the installed grpcio-tools {installed}: "
        "install the version in constraints.txt, or regenerate with tools/gen_stubs.py"
    )
    written = gen.generate(tmp_path)
    assert any(p.name == "agents_pb2_grpc.py" for p in written)
    diff = gen.differences(committed, tmp_path)
    assert not diff, "stale stubs; run `python tools/gen_stubs.py`:\n" + "\n".join(diff)


def test_generated_imports_go_through_the_package(tmp_path: Path) -> None:
    gen = _gen_stubs()
    gen.generate(tmp_path)
    text = (tmp_path / "mcapi" / "v1" / "agents_pb2_grpc.py").read_text()
    assert "from mcapi_client._proto.mcapi.v1 import agents_pb2" in text
    assert "\nfrom mcapi.v1 import" not in text


def test_check_mode_reports_a_difference(tmp_path: Path) -> None:
    gen = _gen_stubs()
    gen.generate(tmp_path)
    assert gen.main(["--check", "--out", str(tmp_path)]) == 0
    stub = tmp_path / "mcapi" / "v1" / "agents_pb2.py"
    stub.write_text(stub.read_text() + "# edited\n")
    assert gen.main(["--check", "--out", str(tmp_path)]) == 1
