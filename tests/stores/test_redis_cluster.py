"""Redis Cluster: the adapters on a real 3-primary cluster on 127.0.0.1 (``LocalCluster``; the store, queue and
key contracts run on it too, see ``conftest.py``), cluster URLs, and a check that every Lua script touches keys
of one slot only, read from MONITOR on a single redis-server (a cluster node refuses only keys held by another
node, so a script reaching into another slot of the same node would pass a cluster test unseen)."""

from __future__ import annotations

import re
import threading
import time

import numpy as np
import pytest
import redis
from redis_server import LocalCluster, RedisServer, free_port
from store_cases import MAP, make_object, step_frame
from test_queue_contract import frame

from arcloud.core.change import MapChange
from arcloud.core.step import integrate_frame
from arcloud.core.types import Params
from arcloud.errors import InvalidInput, StoreUnavailable
from arcloud.ports import QueueLimits
from arcloud.stores import keys
from arcloud.stores.redis import RedisStore, cluster_nodes, connect_redis
from arcloud.stores.redis_api_keys import RedisKeyStore
from arcloud.stores.redis_queue import RedisFrameQueue
from arcloud.stores.redis_rate import RedisRateLimiter

pytestmark = pytest.mark.redis


def test_cluster_urls_name_nodes_and_credentials() -> None:
    assert cluster_nodes("redis+cluster://10.0.0.1:7000,10.0.0.2:7001") == ([("10.0.0.1", 7000), ("10.0.0.2", 7001)], None, None)
    assert cluster_nodes("rediss+cluster://app:p%40ss@[::1]:7000/0") == ([("::1", 7000)], "app", "p@ss")
    with pytest.raises(InvalidInput, match="a cluster has database 0 only"):
        cluster_nodes("redis+cluster://h:7000/2")
    with pytest.raises(InvalidInput, match="got node 'h'"):
        cluster_nodes("redis+cluster://h:7000,h")
    with pytest.raises(InvalidInput, match="url: expected a redis://, rediss://, unix://, redis\\+cluster://"):
        connect_redis("http://h:1")


def test_an_unreachable_cluster_is_store_unavailable() -> None:
    with pytest.raises(StoreUnavailable, match=f"redis at cluster 127.0.0.1:{(port := free_port())} unreachable"):
        connect_redis(f"redis+cluster://127.0.0.1:{port}", reply_timeout_s=0.5)


def test_the_shards_of_a_queue_sit_on_every_primary_and_a_map_on_one(redis_cluster: LocalCluster) -> None:
    redis_cluster.flush()
    queue = RedisFrameQueue(redis_cluster.url, shards=3)
    store = RedisStore(client=queue.client)
    try:
        queue.prepare()
        client = queue.client
        assert isinstance(client, redis.cluster.RedisCluster)
        homes = {client.get_node_from_key(keys.ingest_stream(queue.shard_tag(k))).name for k in range(3)}
        assert len(homes) == 3  # shard_tag spreads the shards' slots over the equal ranges of the primaries
        store.commit(MAP, [], MapChange.writing(MAP, [make_object(1, (0.1, 0.1, 0.1)), make_object(2, (3.0, 0.0, 0.0))]))
        map_keys = [k for node in redis_cluster.nodes for k in node.client().keys(f"arcloud:{{{MAP}}}:*")]
        assert len(map_keys) > 5 and len({client.get_node_from_key(k).name for k in map_keys}) == 1
        assert "cluster 127.0.0.1:" in repr(store)
    finally:
        queue.close()


# --- every script's keys in one slot -----------------------------------------------------------------
_ARG = re.compile(rb'"((?:[^"\\]|\\.)*)"')


class Monitor:
    """The commands a redis-server runs, as MONITOR reports them: (source, args), source "lua" for a
    script's calls, the client's address otherwise."""

    def __init__(self, server: RedisServer) -> None:
        self.client = server.client()
        self.lines: list[bytes] = []
        self.connection = self.client.connection_pool.get_connection()
        self.connection.send_command("MONITOR")
        assert self.connection.read_response() == b"OK"
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        try:
            while True:
                self.lines.append(self.connection.read_response(disable_decoding=True))
        except (redis.exceptions.ConnectionError, OSError, ValueError):
            return  # closed

    def stop(self) -> list[tuple[str, list[bytes]]]:
        """Every command run up to now. MONITOR reports an ECHO sent last after every command before it: the reader
        thread, which can lag behind Redis on a loaded machine, has read them all when it has read the ECHO (closing at
        once lost the last scripts' lines: 6 scripts of 8 seen, on two test processes under load)."""
        marker = b"arcloud-monitor-stop"
        self.client.echo(marker)
        deadline = time.monotonic() + 30
        while not any(marker in line for line in self.lines):
            assert self.thread.is_alive() and time.monotonic() < deadline, "MONITOR did not report the last ECHO"
            time.sleep(0.01)
        self.connection.disconnect()
        self.thread.join(5)
        self.client.close()
        commands = []
        for line in self.lines:
            source = line.split(b"]", 1)[0].rsplit(b" ", 1)[-1].decode()
            args = [re.sub(rb"\\(.)", rb"\1", m) for m in _ARG.findall(line)]
            commands.append((source, args))
        return commands


def test_every_script_touches_keys_of_one_slot_only(redis_server: RedisServer) -> None:
    """The store's, the queue's and the rate limiter's scripts, through a working day: steps on a map,
    queries, deletions, a frame given up, frames queued, taken, acknowledged, dead-lettered, retried, a map deleted."""
    with redis_server.client() as client:
        client.flushdb()
    monitor = Monitor(redis_server)
    store = RedisStore(redis_server.url, cell_m=0.5)
    queue = RedisFrameQueue(client=store.client, shards=3, limits=QueueLimits(max_dead_letters=1))
    try:
        queue.prepare()
        params = Params(index_cell_m=0.5)
        for index in range(3):
            integrate_frame(*step_frame(0, index), store, params)
        store.query_region(MAP, np.full(3, -1.0), np.full(3, 4.0))
        (first, *_) = store.list_objects(MAP)
        with store.lock(MAP, [first.id], ttl_s=5, timeout_s=1) as lease:
            store.commit(MAP, [lease], MapChange.writing(MAP, [], [first]), frame_key="d/x", entry_id="1-0")
        store.give_up_frame(MAP, "d/y", "2-0")
        with store.claim(MAP, [(0, 0, 0), (0, 1, 0)], ttl_s=5, timeout_s=1):
            pass
        for index, map_id in enumerate(("a", "walk", "b", "b")):
            queue.put(frame(index, map_id=map_id))
        for n in range(4):
            item = queue.take("c1", block_s=0.1)
            assert item is not None
            if n % 2:
                queue.dead_letter(item, "poison")
            else:
                queue.ack(item, redelivered=False)
        for map_id in ("walk", "b"):
            for failed in queue.failed_frames(map_id, 10):
                if failed.retriable:
                    queue.retry_failed(map_id, failed.frame_key)
        RedisRateLimiter(client=store.client).take("key:k", rate_per_s=1.0, burst=2)
        RedisKeyStore(client=store.client).list_keys()
        store.delete_map(MAP)
    finally:
        queue.close()
        store.close()
    commands = monitor.stop()
    with redis_server.client() as client:
        assert (
            _check_scripts(commands, client) == 10
        )  # acquire release query commit give_up_frame accept settle dead_letters_kept rate_limit mark_published (delete_map's only one)
        stray = [("c", [b"EVALSHA", b"sha", b"1", b"a{m}"]), ("lua", [b"GET", b"a{m}"]), ("lua", [b"GET", b"b{n}"])]
        with pytest.raises(AssertionError, match="touched 'b{n}' of another slot"):
            _check_scripts(stray, client)  # the check sees what it is for


def _check_scripts(commands: list[tuple[str, list[bytes]]], client: redis.Redis) -> int:
    """Fails on a script whose calls reach a slot other than its declared keys'; returns how many distinct
    scripts were checked."""
    checked: set[bytes] = set()
    script: tuple[bytes, int] | None = None  # (sha, slot) of the script whose calls follow
    for source, args in commands:
        if source != "lua":
            script = None
            if args and args[0].upper() in (b"EVALSHA", b"EVAL"):
                declared = args[3 : 3 + int(args[2])]
                slots = {keys.cluster_slot(k.decode()) for k in declared}
                assert len(slots) == 1, f"script {args[1][:12]!r} declares keys of {len(slots)} slots: {declared}"
                script = (args[1], slots.pop())
            continue
        assert script is not None, f"a script's call without its EVALSHA: {args}"
        if args[0].upper() in (b"TIME",):
            continue
        for key in client.execute_command("COMMAND GETKEYS", *args):
            key = key.decode() if isinstance(key, bytes) else key
            assert keys.cluster_slot(key) == script[1], f"script {script[0][:12]!r} touched {key!r} of another slot"
        checked.add(script[0])
    return len(checked)


def test_the_memory_checks_read_every_primary(redis_cluster: LocalCluster) -> None:
    """A review: INFO went to one node of a cluster, so an evicting or full primary among the others passed."""
    from arcloud.errors import StoreError
    from arcloud.stores.redis import check_memory_policy, connect_redis, memory_full, memory_reports

    client = connect_redis(redis_cluster.url)
    other = redis.Redis(port=redis_cluster.nodes[-1].port)
    try:
        assert len(memory_reports(client)) == len(redis_cluster.nodes)
        other.config_set("maxmemory", 100 * 2**20)
        other.config_set("maxmemory-policy", "allkeys-lru")
        with pytest.raises(StoreError, match="evicts keys when full"):
            check_memory_policy(client)
        other.config_set("maxmemory-policy", "noeviction")
        check_memory_policy(client)
        assert not memory_full(client)
        other.config_set("maxmemory", 1)
        assert memory_full(client).endswith("bytes used of its maxmemory 1: writes are refused until memory is freed or raised")
    finally:
        other.config_set("maxmemory", 0)
        client.close()
