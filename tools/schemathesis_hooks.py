"""Schemathesis hooks of `make contract` (tools/contract.sh).

One check, `schema_valid_body_parses`: a request schemathesis generated as
valid (positive mode) must never be refused as *malformed*. The server
refuses a body that parses but means nothing (an unknown state, a model
whose `next` has the wrong number of rows, ...) with 400 and a semantic
code (`invalid_model`, `unknown_state`, ...); schemathesis' own
`positive_data_acceptance` check cannot tell those apart from a parse
failure, so tools/schemathesis.toml lets `create_session`, `observe`,
`create_group`, `step_group` and `get_values` (whose `include=r` or `xi`
a continuous session refuses: it has no such table) answer 400, and this
check keeps the contract exact: a 400 whose message is
a parse error (serde's `missing field`, `unknown field`, `invalid type`,
...), or any 400 to an operation whose parameters have no semantic
constraint, means the document and the parser disagree.
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
NO_SEMANTIC_400 = {
    "list_sessions",
    "get_session",
    "delete_session",
    "get_history",
    "get_events",
    "get_group",
    "delete_group",
}


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
