"""The service's composition root and tools: the only code that chooses adapters for it.

- ``wiring``: adapters from ``Settings`` (store, frame queue, detector with ``sim:SEED``, Zenoh
  publisher) handed to ``arcloud.service``; the uvicorn factory ``arcloud.tools.wiring:create_app``,
  worker runner and worker processes.
- ``worker``: ``python -m arcloud.tools.worker``, one ingest worker (the containers' entry point).
- ``service_cli``: the ``arcloud serve | worker | replay`` commands.
- ``frames_cli``: the ``arcloud frames failed | retry`` commands (operators, on the Redis queue).
- ``models_cli``: the ``arcloud models list | pull | verify | path`` commands (the model catalogue and cache).
- ``replay``: stream a simulated room through a running service and score the map.

Layers point one way: core <- ports <- adapters (stores, detectors, events) <- service <- tools.
Import the submodules; nothing is imported eagerly.
"""
