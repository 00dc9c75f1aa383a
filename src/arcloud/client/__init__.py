"""Python SDK of the arcloud service: ``ArcloudClient`` (blocking), ``AsyncArcloudClient`` (asyncio),
``ServiceError``, ``frame_body`` (a frame's protobuf bytes, for ``AsyncArcloudClient.send_encoded``);
object events over Zenoh with ``subscribe``. What the clients answer: ``arcloud.client.results`` (typed results, the
events of ``events``).

The base install (``pip install arcloud``) is enough for the HTTP client; ``subscribe`` needs
``arcloud[events]``. The exported names are pinned by ``tests/test_public_api.py``.
"""

from arcloud.client.http import ArcloudClient, AsyncArcloudClient, ServiceError, frame_body, subscribe

__all__ = ["ArcloudClient", "AsyncArcloudClient", "ServiceError", "frame_body", "subscribe"]
