"""Health, readiness, the OpenAPI document and the problem types every error points to."""
from __future__ import annotations

import os

from service_fixtures import free_port, make_api


def test_health_and_readiness(tmp_path):
    api = make_api(tmp_path)
    assert api.client.get("/health").json()["status"] == "ok"
    ready = api.client.get("/ready")
    assert ready.status_code == 200
    assert ready.json()["checks"] == {"database": "ok", "blob_store": "ok", "bundles": "ok", "broker": "ok"}


def test_not_ready_when_the_broker_is_unreachable(tmp_path):
    api = make_api(tmp_path, broker_url=f"redis://127.0.0.1:{free_port()}/0")  # nothing listens there
    response = api.client.get("/ready")
    assert response.status_code == 503 and response.headers["content-type"] == "application/problem+json"
    assert [error["field"] for error in response.json()["errors"]] == ["broker"]


def test_openapi_documents_every_resource(tmp_path):
    api = make_api(tmp_path)
    document = api.client.get("/openapi.json").json()
    paths = document["paths"]
    for path in ("/v1/assets/characters", "/v1/assets/cloth", "/v1/assets/textures", "/v1/bakes", "/v1/bakes/{bake_id}",
                 "/v1/bakes/{bake_id}/cancel", "/v1/bakes/{bake_id}/retry", "/v1/bundles/{name}/{version}/manifest.json",
                 "/v1/bundles/{name}/{version}/files/{path}", "/health", "/ready"):
        assert path in paths, path
    cloth_body = paths["/v1/assets/cloth"]["post"]["requestBody"]["content"]["multipart/form-data"]["schema"]
    assert set(cloth_body["properties"]) == {"cache", "mesh", "sequence", "cycle_frames"}
    assert "application/problem+json" in paths["/v1/bakes"]["post"]["responses"]["422"]["content"]
    assert {"BakeCreate", "BakePublic", "AssetPublic", "BundlePublic", "Problem"} <= set(document["components"]["schemas"])
    schemes = document["components"]["securitySchemes"]
    assert {scheme["type"] for scheme in schemes.values()} == {"apiKey", "http"}


def test_every_problem_type_is_described(tmp_path):
    api = make_api(tmp_path)
    unknown = api.client.get("/v1/nothing-here")
    assert unknown.status_code == 404 and unknown.json()["type"] == "/problems/not-found"
    described = api.client.get(unknown.json()["type"]).json()
    assert described["status"] == 404 and described["title"] == unknown.json()["title"]
    wrong_method = api.client.delete("/v1/bakes")
    assert wrong_method.status_code == 405 and wrong_method.headers["content-type"] == "application/problem+json"


# ------------------------------------------------------------------------------ schema-driven fuzz


def test_no_generated_request_gets_a_server_error(tmp_path):
    """Requests generated from the OpenAPI document (schemathesis), with a key of every scope: whatever
    they send, the answer is never a 500, and every error is a problem document. CROWDBAKE_FUZZ_EXAMPLES
    (default 5) sets the examples per operation, for a longer hunt than CI's."""
    import schemathesis
    from hypothesis import HealthCheck, given, settings

    from service_fixtures import publish_vector_bundle

    api = make_api(tmp_path)
    publish_vector_bundle(api, public=True)
    schema = schemathesis.openapi.from_asgi("/openapi.json", api.client.app)
    checked = 0
    for result in schema.get_all_operations():
        operation = result.ok()

        @given(case=operation.as_strategy())
        @settings(max_examples=int(os.environ.get("CROWDBAKE_FUZZ_EXAMPLES", "5")), deadline=None, suppress_health_check=list(HealthCheck), database=None)
        def check(case):
            case.headers = {**(case.headers or {}), "Authorization": f"Bearer {api.keys['all']}"}
            response = case.call()
            assert response.status_code < 500, (case.method, case.formatted_path, response.text[:300])
            if response.status_code >= 400:
                content_type = response.headers.get("content-type")
                content_type = content_type[0] if isinstance(content_type, list) else content_type
                assert content_type == "application/problem+json", (case.method, case.formatted_path, response.status_code)

        check()
        checked += 1
    assert checked >= 19  # every operation of the document was exercised
