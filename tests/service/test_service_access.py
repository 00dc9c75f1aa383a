"""Keys, roles and rate limits through the real app: on a real redis-server as ``serve --redis`` runs it
(keys required by default), keys made by the real ``arcloud keys`` command; the embedded service with a
keys file; the SDK carrying its token over real HTTP."""

from __future__ import annotations

import logging
import random
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import svc_helpers
from redis_server import RedisServer
from svc_helpers import AppClient, BlobDetector, UvicornThread, make_test_frame

from arcloud.cli import main as cli_main
from arcloud.client.http import ArcloudClient, ServiceError
from arcloud.errors import ArcloudError
from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.tools.service_cli import check_exposure
from arcloud.tools.wiring import create_app

PROTOBUF = {"content-type": "application/x-protobuf"}


def frame_body(map_id: str, index: int = 0, device_id: str = "d") -> bytes:
    return frame_to_proto(make_test_frame(index, map_id=map_id, device_id=device_id)).SerializeToString()  # type: ignore[no-any-return]  # protobuf's stubs


def bearer(token: str) -> dict[str, str]:
    return {"authorization": f"Bearer {token}"}


def create_key(capsys: pytest.CaptureFixture[str], *where: str, maps: str, role: str) -> str:
    """A new key made by the `arcloud keys create` command; its token (the command's only stdout)."""
    capsys.readouterr()
    assert cli_main(["keys", "create", *where, "--maps", maps, "--role", role]) == 0
    token = capsys.readouterr().out.strip()
    assert token.startswith("arc_") and "\n" not in token
    return token


def assert_problem(response: httpx.Response, status: int, field: str | None, *, contains: str = "") -> None:
    problem = svc_helpers.assert_problem(response, status, field)
    assert set(problem) == {"type", "title", "status", "detail", "field"} and contains in problem["detail"], problem


@pytest.fixture(scope="module")
def redis_server() -> Iterator[RedisServer]:
    server = RedisServer.start()
    yield server
    server.stop()


@pytest.fixture
def keyed(redis_server: RedisServer) -> Iterator[AppClient]:
    """The API on Redis with its defaults (auth keys), no workers: frames stay queued."""
    import redis

    redis.Redis.from_url(redis_server.url).flushdb()
    settings = Settings(store=redis_server.url, detector="sim:0", workers=0, key_cache_s=0.2)
    assert settings.auth_mode == "keys"
    with AppClient(create_app(settings)) as api:
        yield api


pytestmark = pytest.mark.redis


def test_without_a_valid_token_every_map_route_answers_401_and_probes_stay_open(
    keyed: AppClient, capsys: pytest.CaptureFixture[str], redis_server: RedisServer
) -> None:
    token = create_key(capsys, "--redis", redis_server.url, maps="a", role="admin")
    forged = token[:-4] + ("AAAA" if not token.endswith("AAAA") else "BBBB")
    for headers in ({}, bearer("nonsense"), bearer(forged), {"authorization": f"Basic {token}"}):
        for method, path in [
            ("GET", "/v1/maps/a/objects"),
            ("GET", "/v1/maps/a/objects/1"),
            ("GET", "/v1/maps/a/stats"),
            ("GET", "/v1/maps/a/frames/d/f000000"),
            ("DELETE", "/v1/maps/a"),
        ]:
            response = keyed.request(method, path, headers=headers)
            assert_problem(response, 401, "authorization")
            assert response.headers["www-authenticate"] == "Bearer"
        posted = keyed.post("/v1/maps/a/frames", content=frame_body("a"), headers={**PROTOBUF, **headers})
        assert_problem(posted, 401, "authorization")
    assert keyed.post("/v1/maps/a/frames", content=frame_body("a"), headers={**PROTOBUF, **bearer(token)}).status_code == 202
    for path in ("/healthz", "/readyz", "/metrics"):
        assert keyed.get(path).status_code in (200, 503), path  # answered, not refused (readyz: no workers)
        assert keyed.get(path).status_code != 401


def test_roles_and_maps(keyed: AppClient, capsys: pytest.CaptureFixture[str], redis_server: RedisServer) -> None:
    where = ("--redis", redis_server.url)
    admin = create_key(capsys, *where, maps="*", role="admin")
    device_a = create_key(capsys, *where, maps="a", role="device")
    reader_a = create_key(capsys, *where, maps="a,c", role="reader")
    post = {**PROTOBUF}
    assert keyed.post("/v1/maps/a/frames", content=frame_body("a"), headers={**post, **bearer(device_a)}).status_code == 202
    assert keyed.post("/v1/maps/b/frames", content=frame_body("b"), headers={**post, **bearer(admin)}).status_code == 202

    # A device key of map a: 403 on map b, for reading and writing; it may read its own map, not delete it.
    assert_problem(
        keyed.post("/v1/maps/b/frames", content=frame_body("b", 1), headers={**post, **bearer(device_a)}),
        403,
        "authorization",
        contains="not for map 'b'",
    )
    assert_problem(keyed.get("/v1/maps/b/objects", headers=bearer(device_a)), 403, "authorization")
    assert keyed.get("/v1/maps/a/objects", headers=bearer(device_a)).status_code == 200
    assert keyed.get("/v1/maps/a/frames/d/f000000", headers=bearer(device_a)).json()["status"] == "queued"
    assert_problem(
        keyed.delete("/v1/maps/a", headers=bearer(device_a)), 403, "authorization", contains="device key may not admin"
    )

    # A reader: GET only.
    assert keyed.get("/v1/maps/a/stats", headers=bearer(reader_a)).json()["frames"]["accepted"] == 1
    assert_problem(
        keyed.post("/v1/maps/a/frames", content=frame_body("a", 2), headers={**post, **bearer(reader_a)}),
        403,
        "authorization",
        contains="reader key may not write",
    )
    assert_problem(keyed.delete("/v1/maps/a", headers=bearer(reader_a)), 403, "authorization")
    assert keyed.get("/v1/maps/a/stats", headers=bearer(reader_a)).json()["frames"]["accepted"] == 1  # nothing written

    # Authorisation comes before existence: a key learns nothing about maps that are not its own.
    assert_problem(keyed.get("/v1/maps/secret/objects", headers=bearer(reader_a)), 403, "authorization")
    assert_problem(keyed.get("/v1/maps/c/objects", headers=bearer(reader_a)), 404, None)  # its own map, empty
    assert_problem(keyed.get("/v1/maps/vic%5Ctim/objects", headers=bearer(admin)), 422, "map_id")

    # Admin deletes; a revoked key stops working within key_cache_s.
    assert keyed.delete("/v1/maps/a", headers=bearer(admin)).json()["map_id"] == "a"
    capsys.readouterr()
    assert cli_main(["keys", "list", *where]) == 0
    listing = capsys.readouterr().out
    device_id = device_a.split("_")[1]
    assert device_id in listing and device_a.split("_", 2)[2] not in listing  # ids shown, secrets never
    assert cli_main(["keys", "revoke", *where, device_id]) == 0
    assert "last key" not in capsys.readouterr().err  # other keys remain
    time.sleep(0.3)
    assert_problem(keyed.get("/v1/maps/a/objects", headers=bearer(device_a)), 401, "authorization")
    assert cli_main(["keys", "revoke", *where, device_id]) == 2  # no such key any more: an error, exit 2
    for key_id in [line.split()[0] for line in listing.splitlines()[1:] if line.split()[0] != device_id]:
        assert cli_main(["keys", "revoke", *where, key_id]) == 0
    assert "warning: that was the last key: every request now answers 401 and /readyz 503" in capsys.readouterr().err
    assert (
        keyed.get("/readyz")
        .json()["checks"]["keys"]
        .endswith("or every key was revoked? create or restore keys: docs/service.md, Recovery)")
    )


def test_rate_limits_answer_429_with_retry_after_and_one_map_cannot_take_anothers_share(
    redis_server: RedisServer, capsys: pytest.CaptureFixture[str]
) -> None:
    import redis

    redis.Redis.from_url(redis_server.url).flushdb()
    settings = Settings(
        store=redis_server.url,
        detector="sim:0",
        workers=0,
        key_rate_per_s=1.0,
        key_burst=5,
        map_frame_rate_per_s=0.5,
        map_frame_burst=3,
    )
    flooder = create_key(capsys, "--redis", redis_server.url, maps="a", role="device")
    other = create_key(capsys, "--redis", redis_server.url, maps="a,b", role="device")
    with AppClient(create_app(settings)) as api:
        answers = [
            api.post("/v1/maps/a/frames", content=frame_body("a", i), headers={**PROTOBUF, **bearer(flooder)}) for i in range(6)
        ]
        assert [r.status_code for r in answers[:3]] == [202] * 3
        refused = answers[3]  # the map's burst (3) is spent before the key's (5)
        assert_problem(refused, 429, None, contains="map 'a'")
        assert 1 <= int(refused.headers["retry-after"]) <= 2
        # The same map from another key: refused too (the map's share); another map: accepted.
        assert (
            api.post("/v1/maps/a/frames", content=frame_body("a", 9, "e"), headers={**PROTOBUF, **bearer(other)}).status_code
            == 429
        )
        assert api.post("/v1/maps/b/frames", content=frame_body("b", 0), headers={**PROTOBUF, **bearer(other)}).status_code == 202
        # The key's own limit, on every route: the flooder's 5-request burst is spent (6 requests above).
        limited = api.get("/v1/maps/a/stats", headers=bearer(flooder))
        assert_problem(limited, 429, None, contains=f"key {flooder.split('_')[1]}")
        assert api.get("/v1/maps/a/stats", headers=bearer(other)).json()["frames"]["accepted"] == 3
        time.sleep(float(refused.headers["retry-after"]))
        assert api.post("/v1/maps/a/frames", content=frame_body("a", 7), headers={**PROTOBUF, **bearer(other)}).status_code == 202
        metrics = api.get("/metrics").text
        assert 'status="429"' in metrics


def random_token(rng: random.Random) -> str:
    """A token of the right form that no key has (a spray of guesses)."""
    alphabet = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_-"
    return f"arc_{rng.getrandbits(48):012x}_{''.join(rng.choice(alphabet) for _ in range(43))}"


@pytest.mark.parametrize("where", ["embedded", "redis"])
def test_a_spray_of_invalid_tokens_gets_429_from_its_address_only(
    where: str, redis_server: RedisServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 22: 3,000 random tokens were answered 401 at 453/s, never 429. Failed authentications are limited
    per client address (the memory and the Redis rate limiter); a key from another address is unaffected."""
    import redis

    limits = {"auth_failure_rate_per_s": 0.5, "auth_failure_burst": 5, "key_cache_s": 0.0}
    if where == "redis":
        redis.Redis.from_url(redis_server.url).flushdb()
        token = create_key(capsys, "--redis", redis_server.url, maps="*", role="reader")
        app = create_app(Settings(store=redis_server.url, detector="sim:0", workers=0, **limits))
    else:
        keys_file = tmp_path / "keys.json"
        token = create_key(capsys, "--file", str(keys_file), maps="*", role="reader")
        app = create_app(Settings(detector="sim:0", workers=1, keys_file=str(keys_file), **limits), detector=BlobDetector())
    rng = random.Random(22)
    spray, other = "203.0.113.7", "198.51.100.2"
    with AppClient(app) as api:
        answers = [api.get("/v1/maps", headers=bearer(random_token(rng)), address=spray) for _ in range(20)]
        assert [a.status_code for a in answers] == [401] * 5 + [429] * 15
        refused = answers[5]
        assert_problem(refused, 429, "authorization", contains=f"client {spray} failed to authenticate more than 5 times")
        assert int(refused.headers["retry-after"]) == 2
        # Barred: the address's requests are refused before their token is looked at, a valid one's too.
        assert_problem(api.get("/v1/maps", headers=bearer(token), address=spray), 429, "authorization")
        assert api.get("/v1/maps", address=spray).status_code == 429
        # Another address has its own budget: its key is served, its first bad token a plain 401.
        assert api.get("/v1/maps", headers=bearer(token), address=other).status_code == 200
        assert api.get("/v1/maps", headers=bearer(random_token(rng)), address=other).status_code == 401
        time.sleep(float(refused.headers["retry-after"]))
        assert api.get("/v1/maps", headers=bearer(token), address=spray).status_code == 200
        assert api.get("/v1/maps", headers=bearer(random_token(rng)), address=spray).status_code == 401  # one more try
        assert api.get("/v1/maps", headers=bearer(random_token(rng)), address=spray).status_code == 429


def test_keys_lost_with_redis_data_make_the_service_not_ready_and_log_it_once(
    keyed: AppClient, redis_server: RedisServer, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 22: after a FLUSHALL every upload got 401 while /readyz said ready."""
    import redis

    assert keyed.get("/readyz").json()["checks"]["keys"] == "ok"  # no key yet: a new deployment is not "lost"
    token = create_key(capsys, "--redis", redis_server.url, maps="a", role="device")
    assert keyed.post("/v1/maps/a/frames", content=frame_body("a"), headers={**PROTOBUF, **bearer(token)}).status_code == 202
    assert keyed.get("/readyz").json()["checks"]["keys"] == "ok"
    redis.Redis.from_url(redis_server.url).flushall()
    time.sleep(0.3)  # the key cache (key_cache_s 0.2)
    with caplog.at_level(logging.ERROR, logger="arcloud"):
        assert_problem(
            keyed.post("/v1/maps/a/frames", content=frame_body("a", 1), headers={**PROTOBUF, **bearer(token)}),
            401,
            "authorization",
        )
        probes = [keyed.get("/readyz") for _ in range(3)]
    for probe in probes:
        assert probe.status_code == 503 and probe.headers["retry-after"]
        keys_check = probe.json()["checks"]["keys"]
        assert keys_check.startswith("lost: the key store holds no key where it held 1"), keys_check
        assert "keys: lost" in probe.json()["detail"]
    lost = [r for r in caplog.records if "API keys lost" in r.getMessage()]
    assert len(lost) == 1 and lost[0].levelname == "ERROR"  # one line, not one a probe
    # Keys restored (here: a new one): ready as far as keys go, and a later loss is logged again.
    create_key(capsys, "--redis", redis_server.url, maps="a", role="device")
    assert keyed.get("/readyz").json()["checks"]["keys"] == "ok"


def test_keys_in_a_redis_of_their_own_survive_the_data(redis_server: RedisServer, capsys: pytest.CaptureFixture[str]) -> None:
    import redis

    data = redis.Redis.from_url(redis_server.url)
    data.flushdb()
    with RedisServer.start() as keys_redis:
        token = create_key(capsys, "--redis", keys_redis.url, maps="a", role="device")
        settings = Settings(store=redis_server.url, keys_store=keys_redis.url, detector="sim:0", workers=0, key_cache_s=0.0)
        assert settings.auth_mode == "keys"
        with_password = Settings(store=redis_server.url, keys_store=keys_redis.url.replace("//", "//:s3cret@"))
        assert "s3cret" not in repr(with_password) and "s3cret" not in str(with_password.redacted())
        with AppClient(create_app(settings)) as api:
            upload = {**PROTOBUF, **bearer(token)}
            assert api.post("/v1/maps/a/frames", content=frame_body("a"), headers=upload).status_code == 202
            assert not data.hexists("arcloud:keys", token.split("_")[1])  # the key is not in the maps' Redis
            data.flushall()
            assert api.post("/v1/maps/a/frames", content=frame_body("a", 1), headers=upload).status_code == 202
            assert api.get("/readyz").json()["checks"]["keys"] == "ok"
    with pytest.raises(ValueError, match="keys_store"):
        Settings(store=redis_server.url, keys_store="mysql://h/0")


def test_embedded_service_with_a_keys_file_and_the_sdk_token(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    keys_file = tmp_path / "keys.json"
    token = create_key(capsys, "--file", str(keys_file), maps="room", role="admin")
    settings = Settings(detector="sim:0", workers=1, keys_file=str(keys_file))
    assert settings.auth_mode == "keys"
    with UvicornThread(create_app(settings)) as server:
        with ArcloudClient(server.url, max_retries=0) as anonymous:
            with pytest.raises(ServiceError) as refused:
                anonymous.stats("room")
            assert refused.value.status == 401 and refused.value.field == "authorization"
        with ArcloudClient(server.url, token=token) as client:
            answer = client.send_frame(make_test_frame(0, map_id="room"))
            assert answer.status == "queued"
            client.wait_until_processed("room", n_frames=1, timeout_s=30)
        monkeypatch.setenv("ARCLOUD_TOKEN", token)  # the SDK's default
        with ArcloudClient(server.url) as client:
            assert client.stats("room").frames.processed == 1


def test_serve_refuses_to_expose_an_open_embedded_service() -> None:
    open_embedded = Settings(detector="sim:0")
    check_exposure(open_embedded, "127.0.0.1")  # loopback: fine
    check_exposure(open_embedded, "::1")
    with pytest.raises(ArcloudError, match="--keys-file"):
        check_exposure(open_embedded, "0.0.0.0")
    check_exposure(Settings(detector="sim:0", auth="none"), "0.0.0.0")  # asked for: served, with a warning
    with pytest.raises(ValueError, match="keys_file"):
        Settings(detector="sim:0", auth="keys")  # embedded keys live in a file


def test_keys_command_errors_are_one_line(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert cli_main(["keys", "create", "--file", str(tmp_path / "k.json"), "--maps", "vic\\tim", "--role", "device"]) == 2
    assert "maps" in capsys.readouterr().err
    assert cli_main(["keys", "list", "--redis", "mysql://x"]) == 2
    assert "--redis" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli_main(["keys", "create", "--file", str(tmp_path / "k.json"), "--maps", "a", "--role", "root"])
