"""CLI commands of the service: ``serve``, ``worker`` and ``replay`` (``arcloud.cli`` adds them with
``add_service_commands(subparsers)``; each sets ``handler``). Adapters come from ``tools.wiring``.

    arcloud serve                                        # embedded: one process, in-memory store, loopback only
    arcloud serve --redis redis://127.0.0.1:6379/0 --workers 4 --detector sim:0   # API keys required
    arcloud serve --redis redis://127.0.0.1:6379/0 --workers 14 --api-processes 2  # two API processes on one port
    arcloud worker --redis redis://redis:6379/0          # one more worker process (e.g. in a container)
    arcloud replay --url http://127.0.0.1:8000 --map kitchen --users 10 --seed 0 --out results.json --token TOKEN

Options left out come from ``ARCLOUD_*`` environment variables (``service.settings``).
"""

from __future__ import annotations

import argparse
import difflib
import logging
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from arcloud.argtypes import PARAMS_HELP, non_negative_int, params_overrides, positive_int

log = logging.getLogger(__name__)


def _store_options(parser: argparse.ArgumentParser, *, embedded: bool = True) -> None:
    store = "else the embedded in-memory store" if embedded else "which a worker needs: it takes frames from Redis"
    parser.add_argument("--redis", metavar="URL", help=f"Redis URL (default: $ARCLOUD_STORE, {store})")
    parser.add_argument(
        "--detector", metavar="SPEC", help="sim:SEED, onnx:PATH, maskrcnn:PATH, ... (default: $ARCLOUD_DETECTOR or onnx)"
    )
    parser.add_argument(
        "--zenoh-mode",
        choices=("off", "peer", "client", "router"),
        help="Zenoh session mode (default off; on when endpoints are given)",
    )
    parser.add_argument("--zenoh-listen", metavar="ENDPOINT", action="append", help="e.g. tcp/0.0.0.0:7447 (repeatable)")
    parser.add_argument("--zenoh-connect", metavar="ENDPOINT", action="append", help="e.g. tcp/zenoh:7447 (repeatable)")
    parser.add_argument("--params", metavar="JSON", type=params_overrides, help=PARAMS_HELP)


def add_service_commands(subparsers: argparse._SubParsersAction) -> None:
    serve = subparsers.add_parser(
        "serve",
        help="run the HTTP service (embedded, or on Redis with worker processes)",
        description="The FastAPI service on uvicorn. Embedded by default (one process, worker threads); with --redis, "
        "frames go through a Redis Stream to --workers worker processes started here (0: run them elsewhere).",
    )
    serve.add_argument("--host", default="127.0.0.1", help="bind address (default 127.0.0.1)")
    serve.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    serve.add_argument(
        "--auth",
        choices=("keys", "none"),
        help="keys: map routes need a token (`arcloud keys create`); none: open. Default: keys with --redis or "
        "--keys-file, none embedded (then only on a loopback --host)",
    )
    serve.add_argument("--keys-file", metavar="PATH", help="API keys in this file (`arcloud keys create --file`)")
    serve.add_argument(
        "--workers", type=non_negative_int, help="worker threads (embedded) or processes (Redis); default $ARCLOUD_WORKERS or 2"
    )
    serve.add_argument(
        "--api-processes",
        type=positive_int,
        default=1,
        help="API processes sharing the port (Redis only: the API is stateless there); default 1. One decodes about 130 "
        "VGA frames/s on a core of its own",
    )
    _store_options(serve)
    serve.set_defaults(handler=run_serve)

    worker = subparsers.add_parser(
        "worker",
        help="run one ingest worker process on Redis (more with more processes or containers)",
        description="Reads frames from the Redis ingest stream through the consumer group until SIGTERM.",
    )
    _store_options(worker, embedded=False)
    worker.set_defaults(handler=run_worker_command)

    replay = subparsers.add_parser(
        "replay",
        help="stream a simulated room through a running service as K users and score the map",
        description="The service must run `--detector sim:SEED` with the same seed. Writes mAP of every object (Table 1), "
        "precision, recall and mAP of the served objects (a plain GET), and the room's ground-truth boxes. The map is "
        "kept as it is (a device key may replay into it); --fresh deletes it first (an admin key).",
    )
    replay.add_argument("--url", default="http://127.0.0.1:8000", help="service URL (default http://127.0.0.1:8000)")
    replay.add_argument("--map", dest="map_id", default=None, help="map id (default room<SEED>)")
    replay.add_argument(
        "--fresh", action="store_true", help="delete the map first, so that no earlier frame counts (needs an admin key)"
    )
    replay.add_argument("--users", type=positive_int, default=10, help="concurrent users K (default 10)")
    replay.add_argument("--seed", type=non_negative_int, default=0, help="room, walk and detector seed (default 0)")
    replay.add_argument("--frames", type=positive_int, default=300, help="frames in the walk (default 300)")
    replay.add_argument("--width", type=positive_int, default=640, help="image width (default 640; height 3/4 of it)")
    replay.add_argument("--timeout", type=float, default=1800.0, help="seconds to wait for processing (default 1800)")
    replay.add_argument(
        "--out", type=Path, default=Path("results.json"), help="results JSON (default results.json): scores, counts, ground truth"
    )
    replay.add_argument(
        "--token",
        default=None,
        help="API key token (default $ARCLOUD_TOKEN): a device key of the map (an admin key with --fresh)",
    )
    replay.add_argument("--no-progress", action="store_true", help="no progress bar")
    replay.set_defaults(handler=run_replay_command)


def settings_from_args(args: argparse.Namespace) -> Any:
    """Settings from the environment, overridden by the options given."""
    from arcloud.service.settings import Settings

    overrides: dict[str, Any] = {}
    if args.redis:
        overrides["store"] = args.redis
    if args.detector:
        overrides["detector"] = args.detector
    if getattr(args, "workers", None) is not None:
        overrides["workers"] = args.workers
    if args.params is not None:
        overrides["params"] = args.params
    if getattr(args, "auth", None):
        overrides["auth"] = args.auth
    if getattr(args, "keys_file", None):
        overrides["keys_file"] = args.keys_file
    if args.zenoh_listen:
        overrides["zenoh_listen"] = args.zenoh_listen
    if args.zenoh_connect:
        overrides["zenoh_connect"] = args.zenoh_connect
    if args.zenoh_mode:
        overrides["zenoh_mode"] = args.zenoh_mode
    elif args.zenoh_listen or args.zenoh_connect:
        overrides["zenoh_mode"] = "peer"
    from pydantic import ValidationError

    from arcloud.errors import ArcloudError, InvalidInput
    from arcloud.tools.wiring import check_detector_spec

    for unknown in unknown_variables(os.environ):  # a warning, not a refusal: the environment is not all ours
        log.warning("%s, ignored", unknown)
    problems: list[str] = []
    settings = None
    try:
        settings = Settings(**overrides)
    except ValidationError as exc:  # the CLI's edge: one line per wrong setting, no traceback
        problems += validation_problems(exc)
    if not any(p.startswith("detector:") for p in problems):  # its form is right: is it a detector we have?
        try:
            check_detector_spec(settings.detector if settings is not None else overrides.get("detector") or _detector_from_env())
        except InvalidInput as exc:
            problems.append(str(exc))
    if problems:
        raise ArcloudError(f"invalid settings (options or ARCLOUD_* variables): {'; '.join(problems)}")
    return settings


#: The variables Kubernetes gives a pod for each Service of its namespace (service links): for a Service
#: ``arcloud-api``, ``ARCLOUD_API_SERVICE_HOST``, ``ARCLOUD_API_PORT_8000_TCP_ADDR`` and so on.
SERVICE_LINK = re.compile(r"_(SERVICE_HOST|SERVICE_PORT(_[A-Z0-9_]+)?|PORT(_\d+_(TCP|UDP|SCTP)(_(ADDR|PORT|PROTO))?)?)$")


def unknown_variables(environ: Mapping[str, str]) -> list[str]:
    """The ``ARCLOUD_*`` variables in ``environ`` that name no setting nor another variable arcloud reads (nor a
    Kubernetes service link), each with the name it may have meant: a mistyped ``ARCLOUD_WORKER=3`` started 2
    workers without a word."""
    from arcloud.client.http import TOKEN_ENV
    from arcloud.detectors.catalogue import MODELS_ENV_VAR
    from arcloud.detectors.factory import MODEL_ENV_VAR
    from arcloud.service.settings import Settings

    known = {f"ARCLOUD_{name.upper()}" for name in Settings.model_fields} | {
        TOKEN_ENV, MODEL_ENV_VAR, MODELS_ENV_VAR, "ARCLOUD_SHARED",  # the SDK's, the model cache's, the data's (bench, tests)
    }  # fmt: skip
    problems = []
    mine = (n for n in environ if n.upper().startswith("ARCLOUD_") and n.upper() not in known)
    for name in sorted(n for n in mine if not SERVICE_LINK.search(n.upper())):
        close = difflib.get_close_matches(name.upper()[8:], sorted(k[8:] for k in known), n=1, cutoff=0.75)
        problems.append(f"{name}: no such setting" + (f" (did you mean ARCLOUD_{close[0]}?)" if close else ""))
    return problems


def validation_problems(exc: Any) -> list[str]:
    """A pydantic ``ValidationError`` of the settings as one line per wrong setting."""
    problems = []
    for error in exc.errors():
        where = ".".join(str(p) for p in error["loc"]) or "settings"
        message = error["msg"].removeprefix("Value error, ")
        problems.append(message if message.startswith((f"{where}:", f"{where}.")) else f"{where}: {message}")
    return problems


def _detector_from_env() -> str:
    """The detector spec the settings would read when none is given on the command line."""
    from arcloud.service.settings import Settings

    return os.environ.get("ARCLOUD_DETECTOR", Settings.model_fields["detector"].default)


def run_serve(args: argparse.Namespace) -> int:

    from arcloud.errors import ArcloudError
    from arcloud.service.logs import configure_logging
    from arcloud.tools.http_server import run_server, run_servers
    from arcloud.tools.wiring import check_model_file, check_redis, check_zenoh_config, create_app

    settings = settings_from_args(args)
    configure_logging(settings.log_level, settings.log_format)
    check_exposure(settings, args.host)
    check_zenoh_config(settings)
    if args.api_processes > 1 and settings.embedded:
        raise ArcloudError("--api-processes N needs --redis: the embedded store and queue live in one process")
    if settings.embedded or settings.workers > 0:
        check_model_file(settings.detector)  # a clear error now, not one per worker after start-up
    check_redis(settings)
    server = {
        "host": args.host,
        "port": args.port,
        "log_level": settings.log_level.lower(),
        "log_config": None,  # uvicorn's lines go through ours: one format, with the time and the request's context
    }
    if args.api_processes > 1:
        run_servers(settings, args.api_processes, **server)
    else:
        run_server(create_app(settings), **server)
    return 0


def check_exposure(settings: Any, host: str) -> None:
    """Refuse to serve without keys beyond loopback unless ``--auth none`` was asked for (then warn)."""
    import ipaddress

    from arcloud.errors import ArcloudError

    if settings.auth_mode != "none":
        return
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if loopback:
        return
    if settings.auth is None:
        raise ArcloudError(
            f"--host {host} exposes the service beyond this machine without API keys: give --keys-file FILE "
            "(`arcloud keys create --file FILE ...`) or --redis URL, or --auth none to serve it open on purpose"
        )
    logging.getLogger("arcloud").warning("--auth none on %s: anyone who reaches it may read, write and delete every map", host)


def run_worker_command(args: argparse.Namespace) -> int:
    from arcloud.service.logs import configure_logging
    from arcloud.tools.wiring import check_model_file, check_redis, check_zenoh_config, run_worker

    settings = settings_from_args(args)
    check_model_file(settings.detector)
    check_zenoh_config(settings)
    check_redis(settings)  # after the files here: then the Redis there
    configure_logging(settings.log_level, settings.log_format)
    run_worker(settings)
    return 0


def run_replay_command(args: argparse.Namespace) -> int:
    from arcloud.tools.replay import replay

    map_id = args.map_id or f"room{args.seed}"
    height = args.width * 3 // 4
    results = replay(
        args.url,
        map_id,
        args.users,
        args.seed,
        args.out,
        n_frames=args.frames,
        width=args.width,
        height=height,
        timeout_s=args.timeout,
        show_progress=not args.no_progress,
        fresh=args.fresh,
        token=args.token,
    )
    row = results["table1"][0]
    frames = results["frames"]
    served = results["served"]
    lost = f", {frames['lost']} lost" if frames["lost"] else ""
    print(
        f"{row['users']} users, {frames['sent']} frames sent, {frames['accepted']} accepted, {frames['processed']} processed{lost} "
        f"in {results['seconds']['stream_and_process']:.1f} s: mAP@0.25 {_fmt(row['map25_mean'])}, mAP@0.5 {_fmt(row['map50_mean'])} "
        f"(every object); served {served['objects']} of {served['objects'] + results['objects']['tentative']} objects: "
        f"precision/recall@0.25 {_fmt(served['precision25'])}/{_fmt(served['recall25'])}, "
        f"@0.5 {_fmt(served['precision50'])}/{_fmt(served['recall50'])} -> {args.out}"
    )
    return 0


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"
