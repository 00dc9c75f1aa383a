"""The cloud service, written against the ports only: FastAPI app (``app.create_app``) and its start and
stop (``runtime``), settings (``settings.Settings``), frame validation (``frames``), the ingest
(``ingest``), the worker loop (``worker``), worker processes (``pool``) and metrics (``metrics``).
Adapters are chosen by ``arcloud.tools.wiring``. Import the submodules; nothing is imported eagerly."""
