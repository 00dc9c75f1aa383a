"""The tests run alone. ``make test`` runs every other test on two processes (``pytest -n 2 --serial skip``,
pytest-xdist), then those that ``SERIAL`` names (``pytest --serial only``), one at a time, nothing else of the
suite running.

They assert bounds on the wall clock, or wait on timers for something to happen: a test on the other process would
take their CPU while they time something (an earlier try of xdist on every test failed a chaos test's PING bound
under load). ``tests/conftest.py`` marks them ``serial`` and adds the option; ``tests/test_serial_tests.py``
checks that every entry still names a test. An entry is a folder, a module, or one test of a module (all its
parametrizations).
"""

from __future__ import annotations

#: What runs alone, and the bound that puts it here.
SERIAL = {
    "tests/chaos/": "PING within 100 ms during hostile requests, recovery and 503 times, client retries within 2 s",
    "tests/stores/test_store_bounded_writes.py": "another client's PING within 100 ms during a large restore and delete",
    "tests/service/test_service_map_deletion.py": "another client's PING within 100 ms while a large map is deleted",
    "tests/service/test_service_uploads.py::test_a_flood_on_one_map_leaves_another_maps_uploads_their_latency": (
        "the flood: another map's p95 latency within 3x of its quiet one"
    ),
    "tests/viewer/test_viewer_page.py": "headless Chromium (its own processes): waits on the page, a load within 10 s",
    "tests/service/test_service_docs.py": "headless Chromium renders Swagger UI and ReDoc within its wait",
    "tests/viewer/test_viewer_events.py": "a keep-alive within 2 s (heartbeat 0.5 s), a revoked key's stream ended within 3 s",
    "tests/events/test_zenoh_access.py": "0.5 s for declarations to reach the router, a refused session within 5 s",
    "tests/stores/test_redis_lock_wakeups.py": "a waiter woken within 1 s of the release, a timeout within 2 s",
    "tests/service/test_service_worker_prefetch.py::test_the_heartbeat_keeps_both_frames_in_hand_fresh": (
        "a heartbeat every 0.1 s keeps the frames in hand idle under 600 ms"
    ),
    "tests/service/test_service_waits.py::test_the_lock_timer_counts_the_time_another_holder_kept_the_objects": (
        "a 0.3 s hold of which at least 0.2 s is waited in the timed call"
    ),
    "tests/stores/test_queue_contract.py::test_a_take_without_waiting_answers_at_once": "10 takes within 0.25 s",
    "tests/stores/test_queue_shards.py::test_a_consumer_waiting_on_an_empty_shard_gets_a_frame_of_another_soon": (
        "a frame of another shard within 0.3 s"
    ),
    "tests/stores/test_queue_shards.py::test_an_abandoned_frame_is_claimed_from_whichever_shard_holds_it": (
        "the frame just claimed is not idle 10 ms later (failed on xdist under load: claimed again)"
    ),
    "tests/stores/test_store_contract.py::test_lock_timeout_waits_then_gives_up_holding_nothing": "gives up within 2 s",
    "tests/stores/test_store_contract.py::test_lock_waits_for_a_release": "takes the lock within 2 s of the release",
    "tests/stores/test_store_contract.py::test_a_waiter_takes_the_lock_when_its_holder_commits": (
        "takes the lock within 1 s of the holder's commit"
    ),
    "tests/stores/test_store_contract.py::test_a_claim_takes_at_most_max_cells_per_call": "refused within 1 s",
    "tests/stores/test_store_contract.py::test_new_ids_cost_the_same_for_any_number": "2**53 ids within 1 s",
}


def is_serial(nodeid: str) -> bool:
    """Whether ``SERIAL`` names the test ``nodeid`` (``tests/x/test_y.py::test_z[param]``), its module or its folder."""
    path, _, name = nodeid.partition("::")
    return any(path.startswith(entry) if "::" not in entry else f"{path}::{name.split('[')[0]}" == entry for entry in SERIAL)
