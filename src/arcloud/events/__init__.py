"""Update publishers: object change events out of the service (``zenoh``). Import the submodule;
nothing is imported eagerly (Zenoh loads with the first session)."""
