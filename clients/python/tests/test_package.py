"""The package as installed: typed, documented, importable on its own."""

from __future__ import annotations

import inspect
import subprocess
import sys
from importlib import resources

import mcapi_client
from mcapi_client import errors, grpc_client, models, rest, types

PUBLIC_MODULES = [mcapi_client, errors, grpc_client, models, rest, types]


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
