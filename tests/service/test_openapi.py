"""schemathesis against the service's OpenAPI schema: every operation, generated requests, no
5xx, and every response (status code, content type, body) as the schema documents it; with
and without a token, and with the reads behind it."""
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import (allow_header_conformance, content_type_conformance,
                                 ignored_auth, missing_required_header, negative_data_rejection,
                                 not_a_server_error, response_headers_conformance,
                                 response_schema_conformance, status_code_conformance)

from running import TOKEN

#: Examples per operation: enough to reach the documented error paths, short enough for CI.
EXAMPLES = 15
#: Not "positive data acceptance": a schema-valid calibration with a rotation that is not a
#: rotation, or a part name that exists nowhere, is rightly refused (422, 404).
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance,
          response_headers_conformance, response_schema_conformance, negative_data_rejection]
#: With a token set, also: a request without it, or with a wrong one, is refused (401).
AUTH_CHECKS = [*CHECKS, allow_header_conformance, ignored_auth, missing_required_header]


def _check_every_operation(url: str, headers: dict | None = None, checks=CHECKS) -> None:
    schema = schemathesis.openapi.from_url(f"{url}/openapi.json")
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) >= 15
    for operation in operations:
        @given(case=operation.as_strategy())
        @settings(max_examples=EXAMPLES, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        def check(case):
            case.call_and_validate(headers=headers, checks=checks)

        try:
            check()
        except Exception as exc:
            pytest.fail(f"{operation.label}: {exc}")


def test_every_endpoint_answers_as_documented(service):
    _check_every_operation(service.url)


@pytest.mark.parametrize("token", [TOKEN, None], ids=["with the token", "without"])
def test_every_endpoint_answers_as_documented_behind_a_token(guarded, token):
    _check_every_operation(guarded.url, {"Authorization": f"Bearer {token}"} if token else None,
                           AUTH_CHECKS if token else CHECKS)


def test_every_status_the_edge_gives_is_declared(service):
    import httpx

    paths = httpx.get(f"{service.url}/openapi.json").json()["paths"]
    for path, methods in paths.items():
        for method, operation in methods.items():
            declared = set(operation["responses"])
            assert {"401", "413", "503"} <= declared, (method, path, declared)
            if method in ("put", "post", "delete"):
                assert {"422", "507"} <= declared, (method, path)


def test_the_api_s_version_is_the_package_s(service):
    """One version, the package's (pyproject.toml), in the API's schema."""
    import tomllib
    from pathlib import Path

    import httpx

    pyproject = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())
    info = httpx.get(f"{service.url}/openapi.json").json()["info"]
    assert info["version"] == pyproject["project"]["version"]
