"""The one boundary between redis-py's exceptions and arcloud's (``arcloud.stores.redis_errors``): every exception
class redis-py defines is decided there, what signals an outage becomes ``StoreUnavailable`` (the API's 503),
and no Redis adapter maps an exception of its own. As httpx tests that its transport maps every httpcore
exception: a redis-py release that adds a class fails here until the table says what it means."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import pytest
from redis import exceptions as rx

from arcloud.errors import StaleLease, StoreError, StoreUnavailable
from arcloud.stores import redis_errors as boundary
from arcloud.stores.redis_errors import REDIS_ERRORS, redis_errors

STORES = Path(boundary.__file__).parent

#: What signals an outage: redis-py's classes that must come out as StoreUnavailable (their subclasses too).
OUTAGES = (
    rx.ConnectionError,
    rx.TimeoutError,
    rx.ReadOnlyError,
    rx.OutOfMemoryError,
    rx.TryAgainError,
    rx.AskError,
    rx.ClusterError,
    rx.RedisClusterException,
)
#: Misuse of the cluster client: bugs, not outages.
BUGS = (rx.CrossSlotTransactionError, rx.InvalidPipelineStack, rx.ClusterCrossSlotError)


def redis_py_exceptions() -> list[type[BaseException]]:
    return [value for value in vars(rx).values() if isinstance(value, type) and issubclass(value, BaseException)]


def instance(cls: type[BaseException]) -> BaseException:
    """An instance of ``cls`` (a redirection's message names the slot and the node)."""
    try:
        return cls("ERR something happened")
    except ValueError:
        return cls("3999 127.0.0.1:7001")


def raised(exc: BaseException) -> BaseException:
    """What ``exc`` becomes when raised inside the boundary."""
    with pytest.raises(StoreError) as caught, redis_errors("do it", "127.0.0.1:6379/0"):
        raise exc
    assert caught.value.__cause__ is exc
    return caught.value


def test_every_exception_class_of_redis_py_is_decided_by_the_table() -> None:
    classes = redis_py_exceptions()
    assert len(classes) > 30  # the walk found redis-py's classes
    unmapped = {c.__name__ for c in classes if c not in REDIS_ERRORS}
    assert not unmapped, f"redis.exceptions classes the boundary does not decide: {sorted(unmapped)}"


@pytest.mark.parametrize("cls", redis_py_exceptions(), ids=lambda c: c.__name__)
def test_every_exception_of_redis_py_becomes_a_store_error_naming_what_and_where(cls: type[BaseException]) -> None:
    exc = instance(cls)
    error = raised(exc)
    assert str(error).startswith("do it: redis at 127.0.0.1:6379/0 ") and str(exc) in str(error)
    outage = issubclass(cls, OUTAGES) and not issubclass(cls, BUGS)
    assert isinstance(error, StoreUnavailable) == outage, (cls.__name__, type(error).__name__)


@pytest.mark.parametrize(
    "message",
    [
        "BUSY Redis is busy running a script. You can only call SCRIPT KILL or SHUTDOWN NOSAVE.",
        "Command # 1 (HGET arcloud:keys 0123456789ab) of pipeline caused error: BUSY Redis is busy running a script.",
        "NOREPLICAS Not enough good replicas to write.",
        "MISCONF Redis is configured to save RDB snapshots, but it's currently unable to persist to disk.",
    ],
)
def test_replies_that_say_not_now_are_unavailable(message: str) -> None:
    error = raised(rx.ResponseError(message))
    assert isinstance(error, StoreUnavailable)
    assert (" busy (" in str(error)) == ("BUSY" in message)


def test_a_failed_fence_is_a_stale_lease_and_other_replies_a_store_error() -> None:
    stale = raised(rx.ResponseError("STALE object 1 written without its lock; nothing written"))
    assert isinstance(stale, StaleLease) and str(stale) == "object 1 written without its lock; nothing written"
    for message in ("ERR unknown command 'FOO'", "WRONGTYPE Operation against a key holding the wrong kind of value", "NOSCRIPT"):
        error = raised(rx.ResponseError(message))
        assert type(error) is StoreError, message


def test_where_is_worked_out_only_when_something_failed() -> None:
    asked: list[str] = []

    def at() -> str:
        asked.append("asked")
        return "cluster 127.0.0.1:7000"

    with redis_errors("ping", at):
        pass
    assert asked == []
    with pytest.raises(StoreUnavailable, match="ping: redis at cluster 127.0.0.1:7000 unreachable"), redis_errors("ping", at):
        raise rx.RedisClusterException("Redis Cluster cannot be connected. Please provide at least one reachable node")
    assert asked == ["asked"]


def test_no_redis_adapter_maps_redis_exceptions_itself() -> None:
    """One mapper: outside ``redis_errors.py`` no Redis adapter raises an arcloud error from a redis-py exception
    it caught (catching one to decide what to do, as NOGROUP or BUSYGROUP, is fine)."""
    pattern = re.compile(r"except[^:\n]*(RedisError|ConnectionError|TimeoutError|RedisClusterException)[^:\n]*:")
    for path in sorted(STORES.glob("redis*.py")):
        if path.name == "redis_errors.py":
            continue
        text = path.read_text()
        assert not pattern.search(text), f"{path.name} catches redis-py's exceptions itself: {pattern.search(text)}"
        assert "raise StoreUnavailable" not in text, f"{path.name} raises StoreUnavailable itself"
    assert inspect.getsource(boundary).count("except ") == 1
