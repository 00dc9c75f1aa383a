"""Schemathesis over every operation of the app's own OpenAPI schema (``app.openapi()``), against the real app
over real HTTP, embedded (auth none) and on a real redis-server (auth keys: an admin token in the fixture's
headers), issue "Safe to expose". Every answer: no 5xx but a 503 with Retry-After, every 4xx/5xx an RFC 9457
problem (``application/problem+json``: type, title, status, detail, field), and the response conforms to the schema
(status code, content type, headers, body); schema-violating input is refused; with auth keys a request without a token or with a wrong one is refused.
Generated strings mix in ``ODD_STRINGS``; frame uploads mix in a valid frame mutated (``frame_strategies``).
Bounded: seeded and derandomized, the examples and coverage phases' cases plus ``MAX_EXAMPLES`` fuzzed cases
per operation.
"""

from __future__ import annotations

from typing import Any

import pytest
import schemathesis
from frame_strategies import multipart_frames, protobuf_frames
from fuzz_helpers import ODD_STRINGS, SEEDED_MAP, FuzzApi, answer_faults
from hypothesis import strategies as st
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import ignored_auth, negative_data_rejection
from schemathesis.transport.serialization import Binary

from arcloud.service.settings import Settings
from arcloud.tools.wiring import create_app

pytestmark = pytest.mark.fuzz

MAX_EXAMPLES = 100
CONFIG = schemathesis.Config.from_dict(
    {
        "seed": 20261123,
        "dictionaries": {"odd": {"values": ODD_STRINGS}},
        "generation": {
            "mode": "all",  # valid and invalid input
            "max-examples": MAX_EXAMPLES,
            "deterministic": True,
            "database": "none",
            "allow-x00": True,
            "dictionaries": {"string": {"dictionary": "odd", "probability": 0.2}},
            # The token is the fixture's (``FuzzApi.headers``): none generated, none removed as "negative" input.
            "with-security-parameters": False,
        },
        # Reproducible: what the next case is never depends on what the server answered before (4xx analysis, values
        # taken from responses), and a slow machine does not fail the run (generation time).
        "phases": {
            "examples": {"extra-data-sources": {"responses": False}},
            "coverage": {"extra-data-sources": {"responses": False}},
            "fuzzing": {"error-feedback": {"enabled": False}, "extra-data-sources": {"responses": False}},
        },
        "suppress-health-check": ["too_slow"],
        # GET .../events never ends: read its first event (the map's snapshot), then close it.
        "max-stream-events": 1,
        # Off: the schema cannot say what a valid frame is (decodable images of one size, a plausible camera), nor
        # which characters ids take (a description says), so schema-valid input may rightly answer 422.
        "checks": {"positive_data_acceptance": {"enabled": False}},
    }
)
# The schema does not depend on the settings: one schema for both apps (building an app starts nothing).
schema = schemathesis.openapi.from_dict(create_app(Settings(detector="sim:0")).openapi(), config=CONFIG)
schemathesis.serializer.alias(
    ["application/x-protobuf", "application/zip"], "application/octet-stream"
)  # the bodies' bytes as they are


@schema.hook
def flatmap_case(context: schemathesis.HookContext, case: schemathesis.Case) -> st.SearchStrategy[schemathesis.Case]:
    """Frame uploads: besides the schema's bodies (random bytes, random parts), a valid frame's protobuf or multipart
    parts mutated (``frame_strategies``). Only positive cases' bodies are replaced: a negative case stays negative."""
    if case.operation.path != "/v1/maps/{map_id}/frames" or case.meta is None or case.meta.generation.mode.is_negative:
        return st.just(case)
    if case.media_type == "application/x-protobuf":
        bodies: st.SearchStrategy[Any] = protobuf_frames().map(FrameBytes)
    elif case.media_type == "multipart/form-data":
        bodies = multipart_frames().map(
            lambda parts: (
                {"meta": parts["meta"][1].decode(errors="replace")}
                | {name: FrameBytes(parts[name][1]) for name in ("rgb", "depth")}
            )
        )
    else:
        return st.just(case)
    return st.one_of(st.just(case), bodies.map(lambda body: with_body(case, body)))


class FrameBytes(Binary):
    """Bytes a ``flatmap_case`` body carries: schemathesis's type for `format: binary` strings, marked as ours."""


def replaced_body(case: schemathesis.Case) -> bool:
    values = case.body.values() if isinstance(case.body, dict) else [case.body]
    return any(isinstance(value, FrameBytes) for value in values)


def with_body(case: schemathesis.Case, body: Any) -> schemathesis.Case:
    derived = case.derive(keep_auth=True)
    derived.body = body
    return derived


def arcloud_answer_rules(ctx: Any, response: schemathesis.Response, case: schemathesis.Case) -> None:
    """No 5xx but a 503 with Retry-After; every 4xx/5xx an RFC 9457 problem."""
    faults = answer_faults(response.status_code, {k: ", ".join(v) for k, v in response.headers.items()}, response.content)
    if faults:
        raise AssertionError("; ".join(faults))


@schema.parametrize()
def test_every_operation(case: schemathesis.Case, fuzz_api: FuzzApi) -> None:
    response = case.call(base_url=fuzz_api.url, session=fuzz_api.session, headers=fuzz_api.headers, timeout=30)
    # not_a_server_error counts every 5xx; arcloud_answer_rules allows a 503 that says when to retry. ignored_auth
    # (with a token: the same request without one, and with a wrong one, answer 401/403) holds only with auth keys:
    # auth none, the embedded default, is open by design though the schema declares the bearer scheme.
    excluded = [not_a_server_error] if fuzz_api.auth else [not_a_server_error, ignored_auth]
    if replaced_body(case):  # schemathesis reads every edited body holding bytes as schema-violating (contains_binary)
        excluded.append(negative_data_rejection)
    case.validate_response(response, headers=fuzz_api.headers, additional_checks=[arcloud_answer_rules], excluded_checks=excluded)
    if case.method == "DELETE" and response.status_code == 200 and case.path_parameters == {"map_id": SEEDED_MAP}:
        fuzz_api.seed()
