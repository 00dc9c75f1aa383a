"""Store and frame-queue adapters: ``memory`` and ``memory_queue`` (embedded, the default), ``redis`` and
``redis_queue`` (Redis Streams; many workers, many machines), with the Redis layout (``keys``), object
encoding (``codec``), stream frame encoding (``stream_frames``) and Lua scripts (``lua/``)."""
