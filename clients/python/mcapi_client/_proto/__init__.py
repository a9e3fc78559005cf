"""Generated gRPC stubs of the mcapi protos (tools/gen_stubs.py; do not edit).

Regenerate with ``python clients/python/tools/gen_stubs.py`` after changing
``proto/``; ``tests/test_stubs.py`` fails while they differ.
"""

GRPCIO_TOOLS_VERSION = "1.85.1"
"""The grpcio-tools version that generated these stubs."""
