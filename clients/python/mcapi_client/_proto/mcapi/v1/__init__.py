"""Generated gRPC stubs of proto/mcapi/v1 (tools/gen_stubs.py; do not edit)."""
