"""``serial_tests.SERIAL`` names tests that exist: an entry left behind by a rename would let its test run beside
others again, with no error."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from serial_tests import SERIAL, is_serial

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("entry", sorted(SERIAL))
def test_every_entry_names_a_folder_a_module_or_a_test_of_one(entry: str) -> None:
    path, _, name = entry.partition("::")
    assert (ROOT / path).is_dir() if path.endswith("/") else (ROOT / path).is_file(), entry
    if name:
        assert re.search(rf"^(async )?def {name}\(", (ROOT / path).read_text(), re.MULTILINE), entry
    assert SERIAL[entry], f"{entry}: say which bound puts it here"


def test_an_entry_names_its_tests_and_no_other() -> None:
    assert is_serial("tests/chaos/test_chaos_bounds.py::test_anything[redis]")
    assert is_serial("tests/stores/test_store_bounded_writes.py::test_anything")
    assert is_serial("tests/stores/test_store_contract.py::test_lock_waits_for_a_release[cluster]")
    assert not is_serial("tests/stores/test_store_contract.py::test_lock_waits_for_a_release_twice[memory]")
    assert not is_serial("tests/stores/test_store_contract.py::test_commit_and_get_round_trip[memory]")
    assert not is_serial("tests/service/test_service_uploads.py::test_a_full_queue_refuses")
