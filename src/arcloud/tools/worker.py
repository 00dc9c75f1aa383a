"""``python -m arcloud.tools.worker``: one ingest worker from ``ARCLOUD_*`` settings until SIGTERM (the
containers' entry point); ``--healthcheck``: exit 0 when a worker of this host wrote a heartbeat lately."""

from __future__ import annotations

import argparse
import logging

from arcloud.errors import ArcloudError
from arcloud.service.logs import configure_logging
from arcloud.service.settings import Settings
from arcloud.tools.wiring import (
    check_detector_spec,
    check_model_file,
    check_redis_policy,
    check_zenoh_config,
    healthy,
    run_worker,
)

log = logging.getLogger(__name__)


def main(argv: list[str] | None = None) -> int:
    """One worker until SIGTERM; ``--healthcheck``: whether this host's worker is alive (exit 0 or 1)."""
    parser = argparse.ArgumentParser(prog="python -m arcloud.tools.worker", description=__doc__)
    parser.add_argument("--healthcheck", action="store_true", help="check this host's worker heartbeat and exit")
    args = parser.parse_args(argv)
    settings = Settings()
    if args.healthcheck:
        if settings.embedded:  # no worker process runs beside the embedded store: nothing to tell alive
            print("unhealthy: ARCLOUD_STORE is no Redis URL (workers take frames from Redis)")
            return 1
        return 0 if healthy(settings) else 1
    configure_logging(settings.log_level, settings.log_format)
    try:
        check_detector_spec(settings.detector)
        check_model_file(settings.detector)
        check_zenoh_config(settings)
        check_redis_policy(settings)  # refused on a Redis that evicts keys; one not answering yet is waited for
        run_worker(settings)  # refused when a live worker maps with other map settings
    except ArcloudError as exc:  # a clear line in the container's log, not a traceback
        log.error("%s", exc)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
