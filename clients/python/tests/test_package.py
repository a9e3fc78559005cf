"""The package as installed: typed, documented, importable on its own, its
transports installed separately (a core with no third-party package, the
`rest` and `grpc` extras)."""

from __future__ import annotations

import inspect
import re
import subprocess
import sys
from importlib import metadata, resources
from pathlib import Path

import pytest

import mcapi_client
from mcapi_client import continuous, errors, groups, grpc_client, models, rest, types, vector_env

PUBLIC_MODULES = [mcapi_client, continuous, errors, groups, grpc_client, models, rest, types, vector_env]


def test_typed_marker_and_stub_types_are_shipped() -> None:
    root = resources.files("mcapi_client")
    assert root.joinpath("py.typed").is_file()
    assert root.joinpath("_proto/mcapi/v1/agents_pb2.pyi").is_file()


def test_every_public_name_has_a_docstring() -> None:
    missing = []
    for module in PUBLIC_MODULES:
        if not (module.__doc__ or "").strip():
            missing.append(module.__name__)
        for name in module.__all__:
            obj = getattr(module, name)
            if inspect.ismodule(obj) or not (inspect.isclass(obj) or inspect.isfunction(obj)):
                continue
            if not (obj.__doc__ or "").strip():
                missing.append(f"{module.__name__}.{name}")
            if inspect.isclass(obj):
                for attr, member in vars(obj).items():
                    if attr.startswith("_") or not callable(member) and not isinstance(member, property):
                        continue
                    if not (getattr(member, "__doc__", None) or "").strip():
                        missing.append(f"{module.__name__}.{name}.{attr}")
    assert not missing, f"public names without a docstring: {missing}"


def test_version_and_exports() -> None:
    assert mcapi_client.__version__ == "0.1.0"
    for name in mcapi_client.__all__:
        assert hasattr(mcapi_client, name), name


def test_imports_without_optional_extras() -> None:
    """The package imports with gymnasium and matplotlib hidden."""
    code = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('gymnasium', 'matplotlib', 'numpy'):\n"
        "            raise ImportError(name)\n"
        "sys.meta_path.insert(0, Block())\n"
        "import mcapi_client\n"
        "from mcapi_client import models\n"
        "print(models.hallway().pairs)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "148"


def _python(code: str, blocked: tuple[str, ...] = (), python: str = sys.executable,
            env: dict[str, str] | None = None) -> str:
    """Runs ``code`` in a fresh interpreter with the modules ``blocked``
    (``sys.modules[name] = None``: importing them fails as if not installed)."""
    prelude = "import sys\n" + "".join(f"sys.modules[{name!r}] = None\n" for name in blocked)
    out = subprocess.run(
        [python, "-c", prelude + code], capture_output=True, text=True, env=env, timeout=60
    )
    assert out.returncode == 0, out.stderr
    return out.stdout


# What the core does without any transport: models, observations, the REST
# requests (sans-I/O), and a clear ImportError naming the extra of each transport.
CORE_CHECK = """
import json
import mcapi_client
from mcapi_client import AgentOptions, McapiError, Observation, models
from mcapi_client._protocol import RestProtocol

op = RestProtocol().observe("s1.X", Observation(25, [0.0, 6.0], "stay"))
print(json.dumps(next(op).json))
print(models.hallway().pairs, AgentOptions(seed=3).to_json())
for name, extra in [("Client", "rest"), ("AsyncClient", "rest"),
                    ("GrpcClient", "grpc"), ("AsyncGrpcClient", "grpc"), ("Interaction", "grpc")]:
    try:
        getattr(mcapi_client, name)
    except ImportError as e:
        hint = "'./clients/python[grpc]'" if extra == "grpc" else "'./clients/python'"
        assert f"pip install {hint}" in str(e), str(e)
        print(name, "needs", extra)
    else:
        raise AssertionError(f"{name} imported without its extra")
try:
    from mcapi_client import GrpcClient  # noqa: F401
except ImportError as e:
    assert "./clients/python[grpc]" in str(e)
else:
    raise AssertionError("GrpcClient imported without grpcio")
loaded = sorted(m for m in sys.modules if m.split(".")[0] in ("httpx", "grpc", "numpy")
                or m.startswith("google.protobuf"))
assert all(sys.modules[m] is None for m in loaded), loaded
"""

CORE_OUTPUT = [
    '{"state": 25, "stimulus": [0.0, 6.0], "action_taken": "stay"}',
    "148 {'seed': 3}",
    "Client needs rest",
    "AsyncClient needs rest",
    "GrpcClient needs grpc",
    "AsyncGrpcClient needs grpc",
    "Interaction needs grpc",
]


def test_the_core_imports_without_any_transport() -> None:
    out = _python(CORE_CHECK, blocked=("httpx", "grpc", "google.protobuf", "numpy"))
    assert out.splitlines() == CORE_OUTPUT


def test_the_core_in_a_fresh_environment(tmp_path: Path) -> None:
    """A virtual environment with nothing installed but this package's files:
    no httpx, grpcio, protobuf or numpy to be found at all."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(tmp_path / "venv")], check=True)
    python = str(tmp_path / "venv" / "bin" / "python")
    (tmp_path / "path").mkdir()
    (tmp_path / "path" / "mcapi_client").symlink_to(Path(mcapi_client.__file__).parent)
    env = {"PYTHONPATH": str(tmp_path / "path"), "PATH": "/usr/bin:/bin"}
    absent = _python(
        "import importlib.util as u\n"
        "print([m for m in ('httpx', 'grpc', 'google.protobuf', 'numpy') if u.find_spec(m.split('.')[0])])",
        python=python, env=env,
    )
    assert absent.strip() == "[]", "the fresh environment has none of the extras' packages"
    assert _python(CORE_CHECK, python=python, env=env).splitlines() == CORE_OUTPUT


def test_grpc_without_httpx_and_rest_without_grpc() -> None:
    """Each transport imports without the other's packages (gRPC does not go
    through the REST module)."""
    out = _python(
        "from mcapi_client import AsyncGrpcClient, GrpcClient, Observation\n"
        "from mcapi_client import _pb\n"
        "print(_pb.observation_message(Observation(3, [1.0])).state)\n"
        "print('mcapi_client.rest' in sys.modules)\n"
        "try:\n"
        "    from mcapi_client import Client\n"
        "except ImportError as e:\n"
        "    print('httpx' in str(e) and './clients/python' in str(e))\n",
        blocked=("httpx",),
    )
    assert out.split() == ["3", "False", "True"]
    for blocked in ("grpc", "google.protobuf"):
        out = _python(
            "from mcapi_client import AsyncClient, Client\n"
            "print('mcapi_client.grpc_client' in sys.modules, 'mcapi_client._pb' in sys.modules)\n"
            "try:\n"
            "    import mcapi_client.grpc_client\n"
            "except ImportError as e:\n"
            "    print('./clients/python[grpc]' in str(e))\n",
            blocked=(blocked,),
        )
        assert out.split() == ["False", "False", "True"], blocked


def test_rest_groups_without_grpc() -> None:
    """Groups over REST need numpy only; the gRPC stream names its extra."""
    out = _python(
        "from mcapi_client import Client, groups, vector_env\n"
        "print(groups.RestVectorAgents.__name__, vector_env.VectorEnvAdapter.__name__)\n"
        "print('mcapi_client._group_grpc' in sys.modules)\n"
        "try:\n"
        "    groups.VectorAgents\n"
        "except ImportError as e:\n"
        "    print('[grpc,vector]' in str(e))\n",
        blocked=("grpc", "google.protobuf"),
    )
    assert out.split() == ["RestVectorAgents", "VectorEnvAdapter", "False", "True"]


def test_the_extras_hold_the_transports() -> None:
    """A plain install has httpx (REST); grpcio and protobuf come with
    `grpc`; `all` is everything the examples use."""
    by_extra: dict[str, set[str]] = {}
    for req in metadata.requires("mcapi-agents-client") or []:
        marker = re.search(r"""extra\s*==\s*["']([\w-]+)["']""", req)
        name = re.match(r"[A-Za-z0-9_.-]+(\[[^]]*\])?", req)
        assert name
        by_extra.setdefault(marker.group(1) if marker else "", set()).add(name.group(0).lower())
    assert by_extra[""] == {"httpx"}, "a plain install can talk REST"
    assert "rest" not in by_extra, "`rest` is an empty extra, kept for old commands"
    assert by_extra["grpc"] == {"grpcio", "protobuf"}
    assert by_extra["vector"] == {"numpy"}, "session groups' columns"
    assert by_extra["all"] == {"mcapi-agents-client[grpc,gymnasium,mo,plot,vector]"}


@pytest.mark.parametrize("name", ["Client", "AsyncClient", "GrpcClient", "AsyncGrpcClient", "AsyncWatch"])
def test_transports_are_exported_lazily(name: str) -> None:
    assert name in mcapi_client.__all__ and name in dir(mcapi_client)
    assert getattr(mcapi_client, name) is getattr(rest if "Grpc" not in name and "Watch" not in name
                                                  else grpc_client, name)
    with pytest.raises(AttributeError):
        mcapi_client.NoSuchThing  # type: ignore[attr-defined]  # noqa: B018
