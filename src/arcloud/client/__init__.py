"""Python SDK of the arcloud service: ``ArcloudClient`` (blocking), ``AsyncArcloudClient`` (asyncio),
``ServiceError``; object events over Zenoh with ``subscribe``."""

from arcloud.client.http import ArcloudClient, AsyncArcloudClient, ServiceError, subscribe

__all__ = ["ArcloudClient", "AsyncArcloudClient", "ServiceError", "subscribe"]
