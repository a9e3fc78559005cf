"""Generated gRPC stubs of proto/mcapi (tools/gen_stubs.py; do not edit)."""
