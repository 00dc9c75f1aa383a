"""The service's settings: one class, read once from ``ARCLOUD_*`` environment variables (or given
explicitly), validated up front so a wrong value stops the service at start with a message naming it.

Examples::

    ARCLOUD_STORE=redis://:secret@redis:6379/0 ARCLOUD_WORKERS=4 ARCLOUD_DETECTOR=onnx:/models/y.onnx
    ARCLOUD_PARAMS='{"voxel_size_m": 0.04}' ARCLOUD_ZENOH_MODE=peer ARCLOUD_ZENOH_LISTEN=tcp/0.0.0.0:7447

Secrets (a password in the Redis URL) are masked in ``repr``/``str`` and in ``redacted()``; log those.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal
from urllib.parse import urlsplit, urlunsplit

from pydantic import Field, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from arcloud.core.types import Params, params_from_json
from arcloud.ports import DEFAULT_FRAME_RECORD_RETENTION_S, DEFAULT_RETIRED_HISTORY_S, QueueLimits
from arcloud.service.logs import LogFormat

STORE_SCHEMES = ("redis", "rediss", "unix", "redis+cluster", "rediss+cluster")  # stores.redis.URL_SCHEMES
ZENOH_CONFIG_TYPES = (".json5", ".json", ".yaml")  # what zenoh.Config.from_file reads
ZenohMode = Literal["off", "peer", "client", "router"]
AuthMode = Literal["keys", "none"]
LogLevel = Literal["DEBUG", "INFO", "WARNING", "ERROR"]
QueuedImages = Literal["decoded", "uploaded"]
#: The most an embedded queued frame holds a pixel: RGB8 and float32 depth (``largest_queued_frame``).
EMBEDDED_BYTES_PER_PIXEL = 7

_URLS = ("store", "keys_store")  # settings that may hold a password (redacted)

# Params fields that are settings of their own here (ARCLOUD_LOCK_TTL_S, ...), not in ``params``.
_PARAMS_OWN = ("lock_ttl_s", "lock_timeout_s")


def redact_url(url: str) -> str:
    """The URL with its password (if any) replaced by ``***`` (a cluster URL's list of nodes kept)."""
    parts = urlsplit(url)
    userinfo, at, hosts = parts.netloc.rpartition("@")
    if not at or ":" not in userinfo:
        return url
    user = userinfo.partition(":")[0]
    return urlunsplit(parts._replace(netloc=f"{user}:***@{hosts}"))


def split_list(value: object) -> object:
    """``"a, b"`` -> ``["a", "b"]`` (environment variables hold comma-separated lists); JSON lists pass."""
    if isinstance(value, str):
        text = value.strip()
        if text.startswith("["):
            import json

            return json.loads(text)
        return [part.strip() for part in text.split(",") if part.strip()]
    return value


class Settings(BaseSettings):
    """Everything the service, its workers and the CLI configure. Frozen once built."""

    model_config = SettingsConfigDict(env_prefix="ARCLOUD_", extra="forbid", frozen=True, hide_input_in_errors=True)

    store: str = Field(
        "memory",
        description="`memory` (embedded, one process), a Redis URL (redis://host:port/db) or a Redis Cluster's "
        "(redis+cluster://host:port,host:port: any of its nodes)",
    )
    detector: str = Field(
        "onnx", description="detector spec: `sim:SEED`, `onnx:PATH` (`onnx` alone: $ARCLOUD_MODEL), `maskrcnn:PATH`, ..."
    )
    detector_threads: int | None = Field(
        None,
        ge=1,
        description="compute threads per worker process (onnxruntime intra-op, simulator ray casting); default: the cores shared among this host's worker processes",
    )
    workers: int = Field(2, ge=0, description="worker threads (memory store) or worker processes (Redis); 0 with Redis: API only")
    max_frame_bytes: int = Field(32 * 2**20, ge=1024, description="largest request body accepted (413 above)")
    max_frame_pixels: int = Field(
        1920 * 1440,
        ge=1,
        description="largest image accepted, in pixels (read from its header before decoding); an encoded image "
        "may take at most twice its pixels' size + 64 KiB, so a queued frame holds at most 10 bytes a pixel + 128 KiB "
        "(`decoded` images: 8 + 64 KiB; embedded: 7), 28 MB at the default",
    )
    queued_images: QueuedImages = Field(
        "uploaded",
        description="how a queue on Redis carries a frame's PNG images: `uploaded`, as they came (a VGA frame: ~180 kB "
        "into and out of Redis instead of ~680 kB, 40 % less Redis CPU), or `decoded`, the pixels the API decoded "
        "to validate them (no worker decodes them again: 2.7 ms less of a worker's CPU a VGA frame, for 0.5 MB more "
        "through Redis; docs/scaling.md). JPEG travels as uploaded either way",
    )
    max_queued_frames: int = Field(
        1000, ge=1, description="frames queued or in progress, all maps together, before ingest answers 503"
    )
    # The rest of the queue's limits (arcloud.ports.QueueLimits; queue_limits() resolves the defaults)
    max_queued_bytes: int = Field(
        2**30,
        ge=1,
        description="bytes of the frames queued or in progress (Redis: stream entries, up to 10 bytes a pixel + 128 KiB; "
        "embedded: their arrays, 7 bytes a pixel) before ingest answers 503",
    )
    max_queued_frames_per_map: int | None = Field(
        None,
        ge=1,
        description="frames of one map queued or in progress before that map's uploads answer 503; default a quarter of "
        "max_queued_frames, so one map cannot take the queue from the others (four busy maps fill it)",
    )
    max_queued_bytes_per_map: int | None = Field(
        None, ge=1, description="the same in bytes; default a quarter of max_queued_bytes"
    )
    frame_record_retention_s: float = Field(
        DEFAULT_FRAME_RECORD_RETENTION_S,
        gt=0,
        description="how long a processed or failed frame is remembered (its status, the duplicate check, the store's "
        "processed mark); after it the frame's status answers 404 and posting it again queues it as new",
    )
    retired_history_s: float = Field(
        DEFAULT_RETIRED_HISTORY_S,
        gt=0,
        description="how long an object the map retired (seen gone: event `removed`) stays in the map's history",
    )
    max_dead_letters: int = Field(10_000, ge=1, description="failed frames kept with their payload for `arcloud frames retry`")
    max_dead_letter_bytes: int = Field(
        2**28, ge=1, description="bytes of those payloads together (the oldest dead letters go first)"
    )
    lock_ttl_s: float = Field(10.0, gt=0, description="per-object lock time to live")
    lock_timeout_s: float = Field(30.0, ge=0, description="how long a step waits for locks")
    params: dict[str, Any] = Field(
        default_factory=dict, description='overrides of arcloud.core.types.Params, e.g. {"voxel_size_m": 0.04}'
    )
    # access (arcloud.access): keys, roles and rate limits
    auth: AuthMode | None = Field(
        None,
        description="`keys`: every route but /healthz, /readyz and /metrics needs `Authorization: Bearer TOKEN` "
        "(`arcloud keys create`); `none`: open to anyone who reaches it. Default: keys with a Redis store or a keys "
        "file, none for the embedded store (which `serve` binds to loopback only)",
    )
    keys_file: str | None = Field(
        None, description="a JSON file of API keys (`arcloud keys create --file`); default with Redis: the keys in Redis"
    )
    keys_store: str | None = Field(
        None,
        description="a Redis URL for the API keys (`arcloud keys create --redis URL`), kept apart from the maps' Redis so "
        "that losing or flushing that one keeps the keys; default: the store's Redis (the HASH arcloud:keys)",
    )
    key_cache_s: float = Field(
        5.0, ge=0, description="how long the API reuses a key lookup: a created or revoked key takes effect within this"
    )
    viewer_ticket_s: float = Field(
        120.0,
        gt=0,
        le=3600,
        description="how long a viewer ticket (POST /v1/maps/{map}/viewer-tickets) may be traded, once, for a viewer session",
    )
    viewer_session_s: float = Field(
        12 * 3600.0,
        gt=0,
        le=7 * 86400,
        description="how long a viewer session (its HttpOnly cookie) reads its map, while the key that drew its ticket may",
    )
    key_rate_per_s: float = Field(
        50.0, ge=0, description="requests a second per key (per client address with auth none), any route; 0: no limit"
    )
    key_burst: int = Field(100, ge=1, description="requests a key may send at once above its rate")
    map_frame_rate_per_s: float = Field(
        60.0, ge=0, description="frame uploads a second per map, from all its devices together; 0: no limit"
    )
    map_frame_burst: int = Field(120, ge=1, description="frame uploads a map may take at once above its rate")
    auth_failure_rate_per_s: float = Field(
        1.0,
        ge=0,
        description="failed authentications (401) a second per client address (auth keys); past them the address's "
        "requests answer 429 with Retry-After, before their token is looked at; 0: no limit",
    )
    auth_failure_burst: int = Field(
        50, ge=1, description="failed authentications a client address may make at once above its rate"
    )
    # what one map or one key may take of an API process (service.uploads, service.event_stream, exports)
    upload_decode_slots: int | None = Field(
        None,
        ge=1,
        description="uploads one API process decodes and checks at once, shared among the maps uploading (a map alone "
        "takes all, two maps half each; one more slot for a map holding none), so a flooded map cannot slow the others' "
        "uploads; more wait their map's turn; default: the process's cores",
    )
    max_uploads_per_map: int = Field(
        16,
        ge=1,
        description="uploads of one map in progress at once in one API process (read, waiting their turn, checked, "
        "queued): 429 beyond, before the body is read",
    )
    max_uploads_per_key: int = Field(
        8,
        ge=1,
        description="uploads of one key (with auth none: one client address) in progress at once: 429 beyond (half a "
        "map's, so that one key sending slowly cannot hold every upload of its map)",
    )
    body_timeout_s: float = Field(
        60.0,
        gt=0,
        description="seconds a request's body may take to arrive, from its first byte: 408 beyond (a client sending a "
        "byte at a time holds no upload for longer)",
    )
    max_exports: int = Field(
        2,
        ge=1,
        description="exports, snapshots and restores one API process runs at once, one key at most all but one of them (each holds a "
        "file in memory: a JSON export with voxels takes about 60 bytes a voxel): 429 with Retry-After beyond",
    )
    max_export_voxels: int = Field(
        1_000_000,
        ge=1,
        description="voxels one export may carry (format=ply, or json with voxels=true): 422 beyond, before any voxel "
        "is read (JSON takes about 9 us and 60 bytes a voxel, PLY 0.2 us and 19 bytes)",
    )
    max_export_objects: int = Field(100_000, ge=1, description="objects one export may carry, any format: 422 beyond")
    max_stats_objects: int = Field(
        10_000,
        ge=1,
        description="objects whose status a map's stats read at most: beyond, `total` stays exact and `confirmed` and "
        "`tentative` count the first of them by id (`truncated`)",
    )
    # object events over HTTP (GET /v1/maps/{map}/events, service.event_stream) and the viewer
    max_event_streams: int = Field(100, ge=1, description="event streams open at once in one API process (503 beyond)")
    max_event_streams_per_key: int = Field(
        10,
        ge=1,
        description="event streams one key (with auth none: one client address) may hold open in one API process "
        "(429 beyond), so that one key cannot take the process's streams from every other map's viewers",
    )
    max_event_streams_per_map: int = Field(
        50, ge=1, description="event streams of one map open at once in one API process (429 beyond)"
    )
    event_poll_s: float = Field(
        0.5, gt=0, le=60, description="how often the API reads a streamed map's change log for what changed"
    )
    event_heartbeat_s: float = Field(
        15.0, gt=0, le=300, description="an idle event stream sends a comment this often (keeps proxies from closing it)"
    )
    # Redis Streams ingest
    consumer_group: str = Field("arcloud-workers", min_length=1)
    ingest_shards: int = Field(
        1,
        ge=1,
        le=1024,
        description="streams the frame queue is split into (a map's frames go to one, by a hash of its id), each with "
        "its consumer group, spread over a Redis Cluster's primaries; the same in every process (the queue keeps it in "
        "Redis and refuses another)",
    )
    claim_min_idle_s: float = Field(60.0, gt=0, description="a pending frame idle this long is claimed by another worker")
    claim_interval_s: float = Field(5.0, gt=0, description="how often a worker looks for abandoned frames")
    max_deliveries: int = Field(5, ge=1, description="deliveries before a frame goes to the dead-letter stream")
    read_block_s: float = Field(1.0, gt=0, description="how long a worker's XREADGROUP blocks")
    worker_prefetch: bool = Field(
        False,
        description="each worker detects its next frame while it integrates the one before (query, locks, fusion, "
        "commit), two frames in hand a worker: for a detector that waits (a GPU, a model server), whose worker "
        "would otherwise idle through the rest of the step. Off (one frame at a time) for CPU sessions: on 16 cores "
        "it measured 0.88-1.07x of off, and doubled one hot map's lock wait (docs/scaling.md)",
    )
    api_redis_timeout_s: float = Field(
        2.0, gt=0, description="how long the API waits on a Redis reply before answering 503 (workers wait 30 s)"
    )
    # Zenoh
    zenoh_mode: ZenohMode = Field("off", description="`off`, or the API's Zenoh session mode (workers always run as clients)")
    zenoh_listen: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="endpoints to listen on, e.g. tcp/0.0.0.0:7447"
    )
    zenoh_connect: Annotated[list[str], NoDecode] = Field(default_factory=list, description="endpoints to connect to (a router)")
    zenoh_frames: bool = Field(
        False,
        description="also accept frames published on arcloud/<map>/frames/<device> (no API key is asked: only with a "
        "router whose access control says who may publish there, docs/service.md)",
    )
    zenoh_config: str | None = Field(
        None,
        description="a Zenoh config file (.json5, .json or .yaml) that every Zenoh session of the API and workers starts "
        "from: credentials (transport/auth/usrpwd) or TLS certificates for a router with access control; mode, endpoints "
        "and multicast scouting are set on top from the zenoh_* settings",
    )
    log_level: LogLevel = "INFO"
    log_format: LogFormat = Field(
        "text",
        description="`text` (a terminal) or `json`: one JSON object a line, with the map, device and frame ids on "
        "every line logged while a frame is processed (arcloud.service.logs)",
    )

    # --- validation --------------------------------------------------------------------------------
    @field_validator("zenoh_listen", "zenoh_connect", mode="before")
    @classmethod
    def _split(cls, value: object) -> object:
        return split_list(value)

    @field_validator("log_format", mode="before")
    @classmethod
    def _lower(cls, value: object) -> object:
        return value.lower() if isinstance(value, str) else value

    @field_validator("log_level", mode="before")
    @classmethod
    def _upper(cls, value: object) -> object:
        return value.upper() if isinstance(value, str) else value

    @field_validator("store")
    @classmethod
    def _check_store(cls, value: str) -> str:
        value = value.strip()
        if value == "memory":
            return value
        scheme = urlsplit(value).scheme
        if scheme not in STORE_SCHEMES:
            raise ValueError(f"expected `memory` or a URL with scheme {'/'.join(STORE_SCHEMES)}, got {redact_url(value)!r}")
        return value

    @field_validator("keys_store")
    @classmethod
    def _check_keys_store(cls, value: str | None) -> str | None:
        if value is None:
            return None
        value = value.strip()
        if urlsplit(value).scheme not in STORE_SCHEMES:
            raise ValueError(f"expected a Redis URL with scheme {'/'.join(STORE_SCHEMES)}, got {redact_url(value)!r}")
        return value

    @field_validator("detector")
    @classmethod
    def _check_detector(cls, value: str) -> str:
        """The spec's form only: which detectors exist is for the composition root to say
        (``arcloud.tools.wiring.check_detector_spec``, run before anything is built)."""
        value = value.strip()
        prefix = value.partition(":")[0]
        if not prefix or not prefix.replace("-", "").replace("_", "").isalnum():
            raise ValueError(f"expected PREFIX[:ARGUMENT] naming a detector, got {value!r}")
        return value

    @field_validator("zenoh_config")
    @classmethod
    def _check_zenoh_config(cls, value: str | None) -> str | None:
        """A readable file of a type Zenoh reads; its content is Zenoh's to check (``arcloud.events.zenoh``)."""
        if value is None:
            return None
        path = Path(value)
        if path.suffix not in ZENOH_CONFIG_TYPES:
            raise ValueError(f"expected a Zenoh config file ({', '.join(ZENOH_CONFIG_TYPES)}), got {value!r}")
        try:
            with path.open("rb") as file:
                file.read(1)
        except OSError as exc:
            raise ValueError(f"expected a readable Zenoh config file, got {value!r} ({exc.strerror or exc})") from None
        return value

    @field_validator("params")
    @classmethod
    def _check_params(cls, value: dict[str, Any]) -> dict[str, Any]:
        """Read as every command reads ``--params`` (``core.types.params_from_json``), less the fields that are
        settings of their own here; kept as read (tuples, floats)."""
        for name in _PARAMS_OWN:
            if name in value:
                raise ValueError(f"params.{name}: set it as its own setting (ARCLOUD_{name.upper()}), not in params")
        params = params_from_json(value)
        return {name: getattr(params, name) for name in value}

    @model_validator(mode="after")
    def _check_combination(self) -> Settings:
        if self.embedded and self.workers < 1:
            raise ValueError("workers: expected >= 1 with the memory store (nothing would process frames), got 0")
        if self.zenoh_mode == "off" and self.zenoh_frames:
            raise ValueError("zenoh_frames: needs zenoh_mode peer, client or router, got zenoh_mode off")
        if self.zenoh_mode == "off" and self.zenoh_config:
            raise ValueError("zenoh_config: needs zenoh_mode peer, client or router, got zenoh_mode off")
        if self.auth == "keys" and self.embedded and not (self.keys_file or self.keys_store):
            raise ValueError("auth: keys with the memory store needs keys_file (the embedded service keeps keys in a file)")
        if self.keys_file and self.keys_store:
            raise ValueError("keys_store: expected either keys_file or keys_store, got both")
        if self.zenoh_mode == "client" and not self.zenoh_connect:
            raise ValueError("zenoh_connect: a Zenoh client needs at least one endpoint to connect to, got none")
        limits = self.queue_limits()
        largest = self.largest_queued_frame()
        for name in ("max_queued_bytes", "max_queued_bytes_per_map"):
            if getattr(limits, name) < largest:
                raise ValueError(
                    f"{name}: expected at least the largest frame ({largest} bytes at max_frame_pixels "
                    f"{self.max_frame_pixels}), got {getattr(limits, name)}"
                )
        return self

    def largest_queued_frame(self) -> int:
        """The most bytes one queued frame can take: embedded, its arrays; on Redis, its colour image as
        uploaded and its depth as uploaded or as pixels (``queued_images=decoded``), each image at most
        ``frames.max_encoded_bytes`` (the protobuf's other fields: a few hundred bytes, in the slack)."""
        from arcloud.service.frames import max_encoded_bytes

        pixels = self.max_frame_pixels
        if self.embedded:
            return EMBEDDED_BYTES_PER_PIXEL * pixels
        depth = 2 * pixels if self.queued_images == "decoded" else max_encoded_bytes(pixels, 1, 2)
        return max_encoded_bytes(pixels, 1, 3) + depth

    # --- derived -----------------------------------------------------------------------------------
    @property
    def embedded(self) -> bool:
        """One process, the in-memory store, worker threads."""
        return self.store == "memory"

    @property
    def queue_decoded_png(self) -> bool:
        """Whether the API puts the pixels of an upload's PNG images in the message it queues (on Redis, with
        ``queued_images=decoded``; the embedded queue takes the decoded frame, not the message)."""
        return not self.embedded and self.queued_images == "decoded"

    @property
    def auth_mode(self) -> AuthMode:
        """``auth``, or its default: keys with Redis, a keys file or a keys store, none embedded."""
        if self.auth is not None:
            return self.auth
        return "keys" if self.keys_file or self.keys_store or not self.embedded else "none"

    def queue_limits(self) -> QueueLimits:
        """The frame queue's limits; a per-map limit left out is a quarter of the overall one."""
        return QueueLimits(
            max_queued_frames=self.max_queued_frames,
            max_queued_bytes=self.max_queued_bytes,
            max_queued_frames_per_map=self.max_queued_frames_per_map or max(1, self.max_queued_frames // 4),
            max_queued_bytes_per_map=self.max_queued_bytes_per_map or max(1, self.max_queued_bytes // 4),
            frame_record_retention_s=self.frame_record_retention_s,
            max_dead_letters=self.max_dead_letters,
            max_dead_letter_bytes=self.max_dead_letter_bytes,
        )

    def make_params(self) -> Params:
        """The frozen algorithm parameters these settings describe."""
        return params_from_json({**self.params, "lock_ttl_s": self.lock_ttl_s, "lock_timeout_s": self.lock_timeout_s})

    def redacted(self) -> dict[str, Any]:
        """The settings as a dict, safe to log (the store URL's password masked)."""
        data = self.model_dump()
        for name in _URLS:
            data[name] = data[name] and redact_url(data[name])
        return data

    def __repr_args__(self) -> Any:
        for name, value in super().__repr_args__():
            yield name, (redact_url(value) if name in _URLS and value else value)


__all__ = ["AuthMode", "Settings", "redact_url"]
