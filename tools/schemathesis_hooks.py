"""Schemathesis hooks of `make contract` (tools/contract.sh).

1. A check, `schema_valid_body_parses`: a request schemathesis generated as
   valid (positive mode) must never be refused as *malformed*. The server
   refuses a body that parses but means nothing (an unknown state, a model
   whose `next` has the wrong number of rows, ...) with 400 and a semantic
   code (`invalid_model`, `unknown_state`, ...); schemathesis' own
   `positive_data_acceptance` check cannot tell those apart from a parse
   failure, so tools/schemathesis.toml lets `create_session` and `observe`
   answer 400, and this check keeps the contract exact: a 400 whose message
   is a parse error (serde's `missing field`, `unknown field`,
   `invalid type`, ...), or any 400 to an operation whose parameters have no
   semantic constraint, means the document and the parser disagree.

2. KNOWN_UNFIXED: inputs that make this build of the server allocate
   without bound (and abort) or spend minutes on one observation before a
   limit refuses them. Their bounds are being added to `Limits` (curiosity
   `tau`, `lag`, `max_centres`, the cost of `signal_dim`; grid source
   dimensions); until then such bodies are not sent (tests/fuzz.rs skips
   the same ones). Remove each entry once its bound is in the server and in
   the document.
"""

import re

import schemathesis

PARSE_ERROR = re.compile(
    r"missing field|unknown field|invalid type|invalid value|invalid length|"
    r"did not match any variant|unknown variant|duplicate field|malformed JSON|"
    r"bad query string|expected `Content-Type"
)

# Operations whose parameters the document describes completely: any 400
# to a schema-valid request is a contract failure.
NO_SEMANTIC_400 = {"list_sessions", "get_session", "delete_session", "get_values", "get_history", "get_events"}

# Known unbounded allocations of this build (see the module docstring).
KNOWN_UNFIXED_CURIOSITY_MAX = {"tau": 100_000, "lag": 100_000, "max_centres": 1024}
KNOWN_UNFIXED_GRID_SOURCE_MAX = 1 << 20
KNOWN_UNFIXED_SIGNAL_DIM_MAX = 16


def _known_unfixed(body):
    if not isinstance(body, dict):
        return False
    model = body.get("model")
    if isinstance(model, dict) and isinstance(model.get("sources"), dict):
        for dim in model["sources"].values():
            if isinstance(dim, (int, float)) and not isinstance(dim, bool) and dim > KNOWN_UNFIXED_GRID_SOURCE_MAX:
                return True
    agent = body.get("agent")
    curiosity = agent.get("curiosity") if isinstance(agent, dict) else None
    params = curiosity.get("params") if isinstance(curiosity, dict) else None
    signal_dim = curiosity.get("signal_dim") if isinstance(curiosity, dict) else None
    if isinstance(signal_dim, (int, float)) and not isinstance(signal_dim, bool) and signal_dim > KNOWN_UNFIXED_SIGNAL_DIM_MAX:
        return True
    if isinstance(params, dict):
        for key, limit in KNOWN_UNFIXED_CURIOSITY_MAX.items():
            value = params.get(key)
            if isinstance(value, (int, float)) and not isinstance(value, bool) and value > limit:
                return True
    return False


@schemathesis.hook
def filter_case(ctx, case):
    if case.operation.path == "/v1/sessions" and case.method.upper() == "POST":
        return not _known_unfixed(case.body)
    return True


@schemathesis.check
def schema_valid_body_parses(ctx, response, case):
    meta = case.meta
    if meta is None or not meta.generation.mode.is_positive:
        return None
    if response.status_code != 400:
        return None
    operation_id = case.operation.definition.raw.get("operationId")
    try:
        message = response.json().get("message", "")
    except Exception:  # noqa: BLE001 - any body that is not our JSON error is a failure
        message = response.text
    if operation_id in NO_SEMANTIC_400:
        raise AssertionError(
            f"`{operation_id}` refused a schema-valid request with 400: {message}"
        )
    if PARSE_ERROR.search(message):
        raise AssertionError(
            f"`{operation_id}` refused a schema-valid request as malformed (the document and "
            f"the parser disagree): {message}"
        )
    return None
