"""schemathesis against the service's OpenAPI schema: every operation, generated requests, no
5xx, and every response (status code, content type, body) as the schema documents it."""
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import (content_type_conformance, negative_data_rejection,
                                 not_a_server_error, response_headers_conformance,
                                 response_schema_conformance, status_code_conformance)

#: Examples per operation: enough to reach the documented error paths, short enough for CI.
EXAMPLES = 15
#: Not "positive data acceptance": a schema-valid calibration with a rotation that is not a
#: rotation, or a part name that exists nowhere, is rightly refused (422, 404).
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance,
          response_headers_conformance, response_schema_conformance, negative_data_rejection]


def test_every_endpoint_answers_as_documented(service):
    schema = schemathesis.openapi.from_url(f"{service.url}/openapi.json")
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) >= 14
    for operation in operations:
        @given(case=operation.as_strategy())
        @settings(max_examples=EXAMPLES, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        def check(case):
            case.call_and_validate(checks=CHECKS)

        try:
            check()
        except Exception as exc:
            pytest.fail(f"{operation.label}: {exc}")
