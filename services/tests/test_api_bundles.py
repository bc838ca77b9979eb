"""Bundle serving through the real app, on the good bundle vector: the URL layout the C++ runtime
relies on, strong ETags that are the sha256, Range and conditional requests, immutable caching, the
`latest` alias, and who may read what. Every test runs on the local bundle folder and, when the tests
have an S3 server, on the object store (files streamed from it, or redirected to presigned URLs)."""
from __future__ import annotations

import hashlib
import json

import pytest

from service_fixtures import GOOD_BUNDLE, STORES, make_api, publish_vector_bundle

MANIFEST = json.loads((GOOD_BUNDLE / "manifest.json").read_bytes())
ENTRY = max(MANIFEST["files"], key=lambda entry: entry["size"])  # the largest file, for ranges


@pytest.fixture(params=STORES)
def api(tmp_path, request):
    api = make_api(tmp_path, request.param)
    api.name, api.version = publish_vector_bundle(api, public=False)
    api.base = f"/v1/bundles/{api.name}/{api.version}"
    return api


def test_manifest_and_every_file_match_their_sha256(api):
    manifest = api.client.get(f"{api.base}/manifest.json", headers=api.auth("read"))
    assert manifest.status_code == 200 and manifest.headers["content-type"].startswith("application/json")
    assert manifest.headers["etag"] == f'"{hashlib.sha256(manifest.content).hexdigest()}"'
    assert manifest.headers["cache-control"] == "private, max-age=31536000, immutable"
    for entry in manifest.json()["files"]:
        response = api.client.get(f"{api.base}/files/{entry['path']}", headers=api.auth("read"))
        assert response.status_code == 200
        assert hashlib.sha256(response.content).hexdigest() == entry["sha256"]
        assert response.headers["etag"] == f'"{entry["sha256"]}"'
        assert response.headers["content-type"].startswith(entry["media_type"])
        assert response.headers["accept-ranges"] == "bytes"


def test_range_requests(api):
    url, data = f"{api.base}/files/{ENTRY['path']}", (GOOD_BUNDLE / ENTRY["path"]).read_bytes()
    partial = api.client.get(url, headers={**api.auth("read"), "Range": "bytes=16-47"})
    assert partial.status_code == 206 and partial.content == data[16:48]
    assert partial.headers["content-range"] == f"bytes 16-47/{len(data)}"
    suffix = api.client.get(url, headers={**api.auth("read"), "Range": "bytes=-10"})
    assert suffix.status_code == 206 and suffix.content == data[-10:]
    unsatisfiable = api.client.get(url, headers={**api.auth("read"), "Range": f"bytes={len(data) + 5}-"})
    assert unsatisfiable.status_code == 416 and unsatisfiable.headers["content-type"] == "application/problem+json"
    assert unsatisfiable.headers["content-range"] == f"bytes */{len(data)}"
    # If-Range with a stale ETag: the whole file, not a piece of a different version
    stale = api.client.get(url, headers={**api.auth("read"), "Range": "bytes=0-3", "If-Range": '"' + "0" * 64 + '"'})
    assert stale.status_code == 200 and stale.content == data
    fresh = api.client.get(url, headers={**api.auth("read"), "Range": "bytes=0-3", "If-Range": f'"{ENTRY["sha256"]}"'})
    assert fresh.status_code == 206 and fresh.content == data[:4]
    garbled = api.client.get(url, headers={**api.auth("read"), "Range": "lines=1-2"})
    assert garbled.status_code == 200 and garbled.content == data  # an unparseable Range is ignored


def test_conditional_and_head(api):
    url = f"{api.base}/files/{ENTRY['path']}"
    etag = f'"{ENTRY["sha256"]}"'
    not_modified = api.client.get(url, headers={**api.auth("read"), "If-None-Match": f'"abc", {etag}'})
    assert not_modified.status_code == 304 and not_modified.content == b"" and not_modified.headers["etag"] == etag
    head = api.client.head(url, headers=api.auth("read"))
    assert head.status_code == 200 and head.content == b"" and int(head.headers["content-length"]) == ENTRY["size"]


def test_latest_alias_revalidates_and_names_the_version(api):
    publish_vector_bundle(api, api.name, "2.0.0", public=False)
    # latest is resolved once: a 307 to the concrete version, for the manifest and for files alike.
    for tail in (f"files/{ENTRY['path']}", "manifest.json"):
        response = api.client.get(f"/v1/bundles/{api.name}/latest/{tail}", headers=api.auth("read"), follow_redirects=False)
        assert response.status_code == 307 and response.headers["cache-control"] == "no-cache"
        assert response.headers["location"] == f"/v1/bundles/{api.name}/2.0.0/{tail}"
        followed = api.client.get(response.headers["location"], headers=api.auth("read"))
        assert followed.status_code == 200 and "immutable" in followed.headers["cache-control"]
    info = api.client.get(f"/v1/bundles/{api.name}/latest", headers=api.auth("read")).json()
    assert info["version"] == "2.0.0"
    versions = api.client.get(f"/v1/bundles/{api.name}", headers=api.auth("read")).json()
    assert versions["latest"] == "2.0.0" and [v["version"] for v in versions["versions"]] == ["2.0.0", api.version]


def test_private_bundles_need_the_read_scope_and_public_ones_do_not(api):
    url = f"{api.base}/manifest.json"
    assert api.client.get(url).status_code == 404  # no key: answered as a missing bundle
    assert api.client.get(url, headers=api.auth("upload")).status_code == 404  # no read scope: nothing revealed
    assert api.client.get("/v1/bundles").json()["names"] == []
    assert api.client.get("/v1/bundles", headers=api.auth("read")).json()["names"] == [api.name]
    assert api.client.patch(api.base, json={"public": True}, headers=api.auth("read")).status_code == 403
    made_public = api.client.patch(api.base, json={"public": True}, headers=api.auth("publish"))
    assert made_public.status_code == 200 and made_public.json()["public"] is True
    anonymous = api.client.get(url)
    assert anonymous.status_code == 200 and anonymous.headers["cache-control"] == "public, max-age=31536000, immutable"
    assert api.client.get("/v1/bundles").json()["names"] == [api.name]


# Dot segments are percent-encoded: an HTTP client would otherwise resolve them before sending.
@pytest.mark.parametrize("path", ["missing.bin", "manifest.json", "%2e%2e/manifest.json", "poses/%2e%2e/%2e%2e/%2e%2e/1.0.0/manifest.json", "%2fetc%2fpasswd"])
def test_only_listed_files_are_served(api, path):
    response = api.client.get(f"{api.base}/files/{path}", headers=api.auth("read"))
    assert response.status_code == 404 and response.headers["content-type"] == "application/problem+json"


def test_unknown_bundles_are_problems(api):
    assert api.client.get("/v1/bundles/nobody/1.0.0/manifest.json", headers=api.auth("read")).status_code == 404
    assert api.client.get("/v1/bundles/Bad Name/1.0.0/manifest.json", headers=api.auth("read")).status_code == 422


@pytest.mark.parametrize("store", STORES)
def test_redirected_downloads_come_from_the_store_with_the_same_bytes(tmp_path, store):
    """CROWDBAKE_S3_REDIRECT_DOWNLOADS: an object store answers file downloads with a 307 to a presigned
    URL (still 304 on a matching ETag, without touching the store); a local store has no such URL and
    keeps streaming."""
    import httpx

    api = make_api(tmp_path, store, s3_redirect_downloads=True)
    name, version = publish_vector_bundle(api, public=True)
    expected = (GOOD_BUNDLE / ENTRY["path"]).read_bytes()
    answer = api.client.get(f"/v1/bundles/{name}/{version}/files/{ENTRY['path']}", follow_redirects=False)
    assert answer.headers["etag"] == f'"{ENTRY["sha256"]}"'
    if store == "local":
        assert answer.status_code == 200 and answer.content == expected
        return
    assert answer.status_code == 307, answer.text
    assert answer.headers["cache-control"].startswith("private, max-age=")
    fetched = httpx.get(answer.headers["location"], headers={"Range": "bytes=10-19"})
    assert fetched.status_code == 206 and fetched.content == expected[10:20]
    assert fetched.headers["content-type"] == ENTRY["media_type"]
    again = api.client.get(f"/v1/bundles/{name}/{version}/files/{ENTRY['path']}", headers={"If-None-Match": answer.headers["etag"]},
                           follow_redirects=False)
    assert again.status_code == 304
