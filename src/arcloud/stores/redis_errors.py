"""The one boundary between redis-py's exceptions and arcloud's, for every Redis adapter (the store, the
frame queue, the API keys, the rate limits)::

    with redis_errors("look the key up", at):   # at: where Redis is ("host:port/db"), or a callable giving it
        client.hget(...)

Whatever redis-py raises in the block is raised again (``from`` it) as one of ``arcloud.errors``:

    StoreUnavailable   Redis cannot serve the command now, and may later: a connection error (refused, reset,
                       authentication, still loading its data, too many connections), a timeout, a reply
                       ``BUSY`` (a script running past busy-reply-threshold), ``NOREPLICAS`` or ``MISCONF`` (writes
                       refused until replicas or the disk come back), ``READONLY`` (a replica after a failover),
                       ``OOM`` (at maxmemory), ``TRYAGAIN``, ``MOVED``, ``ASK``, ``CLUSTERDOWN``, ``MASTERDOWN`` (a cluster
                       moving slots or failing over), and a cluster client that reaches no node or no node
                       serving the slot (``RedisClusterException``, ``SlotNotCoveredError``, ``ClusterError``)
    StaleLease         a store script's fence failed: a reply ``STALE ...`` (nothing was written)
    StoreError         anything else: a command or a script that Redis refused, a reply that cannot be read,
                       a misuse of the client (a cross-slot transaction, a bad argument)

The service answers ``StoreUnavailable`` 503 with ``Retry-After``; workers wait and read again.
``REDIS_ERRORS`` names every exception class of ``redis.exceptions`` (the most specific base listed wins),
and ``tests/stores/test_redis_errors.py`` fails when a redis-py release adds one, so that each is decided here.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

from redis import exceptions as rx

from arcloud.errors import FrameGivenUp, StaleLease, StoreError, StoreUnavailable

#: Each exception class of ``redis.exceptions`` -> what it becomes (a class's most specific listed base decides).
REDIS_ERRORS: dict[type[Exception], type[StoreError]] = {
    # the server cannot be reached or answer in time: try again later
    rx.ConnectionError: StoreUnavailable,
    rx.AuthenticationError: StoreUnavailable,
    rx.AuthorizationError: StoreUnavailable,
    rx.BusyLoadingError: StoreUnavailable,
    rx.MaxConnectionsError: StoreUnavailable,
    rx.ExternalAuthProviderError: StoreUnavailable,
    rx.TimeoutError: StoreUnavailable,
    # replies that say "not now"
    rx.ReadOnlyError: StoreUnavailable,
    rx.OutOfMemoryError: StoreUnavailable,
    rx.TryAgainError: StoreUnavailable,
    rx.AskError: StoreUnavailable,
    rx.MovedError: StoreUnavailable,
    rx.ClusterError: StoreUnavailable,
    rx.ClusterDownError: StoreUnavailable,
    rx.MasterDownError: StoreUnavailable,
    # the cluster client found no node (to read the slot map from, or serving the slot)
    rx.RedisClusterException: StoreUnavailable,
    rx.SlotNotCoveredError: StoreUnavailable,
    # misuse of the cluster client: a bug here, not an outage
    rx.CrossSlotTransactionError: StoreError,
    rx.InvalidPipelineStack: StoreError,
    rx.ClusterCrossSlotError: StoreError,
    # everything else Redis or redis-py refuses (plain ResponseError: see UNAVAILABLE_REPLIES, STALE_REPLY)
    rx.RedisError: StoreError,
    rx.ResponseError: StoreError,
    rx.InvalidResponse: StoreError,
    rx.DataError: StoreError,
    rx.PubSubError: StoreError,
    rx.WatchError: StoreError,
    rx.NoScriptError: StoreError,
    rx.ExecAbortError: StoreError,
    rx.NoPermissionError: StoreError,
    rx.ModuleError: StoreError,
    rx.NoSuchFieldsetError: StoreError,
    rx.AuthenticationWrongNumberOfArgsError: StoreError,
    rx.LockError: StoreError,
    rx.LockNotOwnedError: StoreError,
    rx.ChildDeadlockedError: StoreError,
    rx.IncorrectPolicyType: StoreError,
}
#: Error codes of replies that redis-py raises as a plain ``ResponseError`` and that mean "not now".
UNAVAILABLE_REPLIES = frozenset({"BUSY", "NOREPLICAS", "MISCONF"})
#: The error code of a store script whose fence failed (``lua/commit.lua``).
STALE_REPLY = "STALE"
GIVEN_UP_REPLY = "GIVENUP"  # commit.lua: the frame's queue entry was given up (``FrameGivenUp``)
#: What redis-py puts before a reply's error in a pipeline ("Command # 2 (HGET ...) of pipeline caused error: BUSY ...").
_PIPELINE_ERROR = "caused error: "
_CAUGHT = tuple(REDIS_ERRORS)


def reply_code(exc: BaseException) -> str:
    """The error code a Redis reply starts with ("BUSY", "ERR", ...), alone or inside a pipeline's error; "" for none."""
    message = str(exc)
    if _PIPELINE_ERROR in message:
        message = message.split(_PIPELINE_ERROR, 1)[1]
    return message.split(" ", 1)[0]


def mapped(exc: Exception, doing: str, at: str) -> StoreError:
    """``exc`` (any exception of ``redis.exceptions``) as arcloud's, saying what failed where."""
    code = reply_code(exc) if isinstance(exc, rx.ResponseError) else ""
    if code == STALE_REPLY:
        return StaleLease(str(exc).split(f"{STALE_REPLY} ", 1)[1])
    if code == GIVEN_UP_REPLY:
        return FrameGivenUp(str(exc).split(f"{GIVEN_UP_REPLY} ", 1)[1])
    kind = next((REDIS_ERRORS[c] for c in type(exc).__mro__ if c in REDIS_ERRORS), StoreError)
    if code in UNAVAILABLE_REPLIES:
        kind = StoreUnavailable
    if kind is StoreUnavailable:
        state = "busy" if code == "BUSY" else "unavailable" if code else "unreachable"
        return StoreUnavailable(f"{doing}: redis at {at} {state} ({type(exc).__name__}: {exc})")
    return StoreError(f"{doing}: redis at {at} failed ({type(exc).__name__}: {exc})")


@contextmanager
def redis_errors(doing: str, at: str | Callable[[], str]) -> Iterator[None]:
    """Raise what redis-py raises in the block as arcloud's (``mapped``); ``doing``: what the block does, ``at``:
    where Redis is (a callable: worked out only when something failed)."""
    try:
        yield
    except _CAUGHT as exc:
        raise mapped(exc, doing, at() if callable(at) else at) from exc


__all__ = ["GIVEN_UP_REPLY", "REDIS_ERRORS", "STALE_REPLY", "UNAVAILABLE_REPLIES", "mapped", "redis_errors", "reply_code"]
