"""The cloud service: FastAPI app (``app.create_app``), settings (``settings.Settings``), ingest in
process or through Redis Streams (``ingest``, ``worker``), replay of a simulated room (``replay``) and
the CLI commands (``cli``). Import the submodules; nothing is imported eagerly."""
