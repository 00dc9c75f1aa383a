"""The README's key example, run as written: a `device` key for kitchen,lab made on Redis, `replay` into
kitchen with it (it used to delete the map first: 403 "a device key may not admin"), the key listed, then
revoked. Only the addresses change (a Redis and a service of the test's), and replay gets a short walk."""

from __future__ import annotations

import json
import re
import shlex
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from redis_server import RedisServer
from svc_helpers import UvicornThread, wait_until

from arcloud.cli import main as cli_main
from arcloud.service.settings import Settings
from arcloud.tools.wiring import create_app

pytestmark = [pytest.mark.redis, pytest.mark.slow]

README = Path(__file__).resolve().parents[2] / "README.md"
README_REDIS, README_URL = "redis://127.0.0.1:6379/0", "http://127.0.0.1:8000"
SHORT_WALK = ["--frames", "12", "--width", "160", "--users", "2", "--no-progress"]


def readme_key_commands() -> list[tuple[dict[str, str], list[str]]]:
    """(environment, arguments of `arcloud`) of each line of the README's block that starts with `keys create`."""
    blocks = re.findall(r"```sh\n(.*?)```", README.read_text(), re.S)
    (block,) = [b for b in blocks if "arcloud keys create --redis" in b]
    commands = []
    for line in block.splitlines():
        words = shlex.split(line.split("  #")[0])
        env = dict(w.split("=", 1) for w in words if re.fullmatch(r"[A-Z_]+=\S+", w))
        words = [w for w in words if not re.fullmatch(r"[A-Z_]+=\S+", w)]
        assert words[0] == ".venv/bin/arcloud", line
        commands.append((env, words[1:]))
    return commands


@pytest.fixture
def service() -> Iterator[tuple[str, str]]:
    with RedisServer.start() as redis_server:
        settings = Settings(store=redis_server.url, detector="sim:0", workers=1, key_cache_s=0.2)
        with UvicornThread(create_app(settings)) as server:
            yield redis_server.url, server.url


def test_the_readme_key_example_runs_as_written(
    service: tuple[str, str], tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    redis_url, url = service
    commands = readme_key_commands()
    assert [args[:2] for _, args in commands] == [["keys", "create"], ["replay", "--url"], ["keys", "list"], ["keys", "revoke"]]
    token = key_id = ""
    for env, args in commands:
        args = [{README_REDIS: redis_url, README_URL: url}.get(a, a) for a in args]
        capsys.readouterr()
        if args[0] == "replay":
            assert env == {"ARCLOUD_TOKEN": "arc_..."} and "--fresh" not in args
            monkeypatch.setenv("ARCLOUD_TOKEN", token)
            args += [*SHORT_WALK, "--out", str(tmp_path / "results.json")]
        if args[:2] == ["keys", "revoke"]:
            args[-1] = key_id  # the README's stands for the id `keys list` shows
        assert cli_main(args) == 0, capsys.readouterr().err
        out, err = capsys.readouterr()
        if args[:2] == ["keys", "create"]:
            token, key_id = out.strip(), err.split("created key ")[1].split(":")[0]
        if args[:2] == ["keys", "list"]:
            assert re.search(rf"^{key_id}\s+device\s.*kitchen,lab\s+tablet-7$", out, re.M), out
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["service"]["map_id"] == "kitchen"
    assert results["frames"] == {"sent": 12, "accepted": 12, "duplicate": 0, "processed": 12, "failed": 0, "lost": 0}
    with httpx.Client(base_url=url, headers={"authorization": f"Bearer {token}"}) as http:
        wait_until(lambda: http.get("/v1/maps/kitchen/stats").status_code == 401, 5, "the revoked key refused")


def test_replay_fresh_needs_a_key_that_may_delete(
    service: tuple[str, str], tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """--fresh deletes the map first: an admin key's; a device key is refused before any frame is sent."""
    redis_url, url = service
    assert cli_main(["keys", "create", "--redis", redis_url, "--maps", "kitchen", "--role", "device"]) == 0
    monkeypatch.setenv("ARCLOUD_TOKEN", capsys.readouterr().out.strip())
    argv = ["replay", "--url", url, "--map", "kitchen", "--fresh", *SHORT_WALK, "--out", str(tmp_path / "r.json")]
    assert cli_main(argv) == 2
    err = capsys.readouterr().err
    # other tests' worker threads may still log to stderr: the CLI's own answer is its last line
    assert err.strip().splitlines()[-1].startswith("arcloud: error: HTTP 403") and "admin" in err, err
