"""API keys and roles (``arcloud.access``): tokens, their check, and what each role may do where."""

from __future__ import annotations

import pytest

from arcloud.access import ALL_MAPS, ApiKey, new_key, parse_maps, split_token, verify
from arcloud.errors import InvalidInput


def test_a_new_token_verifies_against_its_key_and_no_other() -> None:
    key, token = new_key("device", ("office",), now_s=100.0, name="tablet")
    other, other_token = new_key("device", ("office",), now_s=100.0)
    parts = split_token(token)
    assert parts is not None and parts[0] == key.id
    assert verify(key, parts[1])
    assert not verify(other, parts[1])
    assert token not in str(key.to_record()) and parts[1] not in str(key.to_record())  # only the digest is kept
    assert ApiKey.from_record(key.to_record()) == key
    assert key.id != other.id and token != other_token


@pytest.mark.parametrize(
    "text", ["", "arc_", "arc_0123456789ab_short", "Bearer arc_0123456789ab_" + "x" * 43, "arc_0123456789AB_" + "x" * 43]
)
def test_malformed_tokens_do_not_split(text: str) -> None:
    assert split_token(text) is None


@pytest.mark.parametrize(
    ("role", "action", "map_id", "allowed"),
    [
        ("reader", "read", "a", True),
        ("reader", "write", "a", False),
        ("reader", "admin", "a", False),
        ("device", "read", "a", True),
        ("device", "write", "a", True),
        ("device", "admin", "a", False),
        ("device", "write", "b", False),  # another map
        ("admin", "admin", "a", True),
        ("admin", "admin", "b", False),
        ("admin", "admin", None, False),  # a route of no map needs a '*' key
    ],
)
def test_what_each_role_may_do_on_its_maps(role: str, action: str, map_id: str | None, allowed: bool) -> None:
    key, _ = new_key(role, ("a",), now_s=0.0)
    assert key.allows(action, map_id) is allowed  # type: ignore[arg-type]  # parametrised strings are the Action literals


def test_a_star_key_covers_every_map() -> None:
    key, _ = new_key("reader", (ALL_MAPS,), now_s=0.0)
    assert key.allows("read", "anything") and key.allows("read", None) and not key.allows("write", "anything")


def test_maps_are_checked_map_ids_or_a_lone_star() -> None:
    assert parse_maps("a, b,a") == ("a", "b")
    assert parse_maps("*") == ("*",)
    for bad in ("", " , ", "a,*", "vic\\tim", "x" * 129):
        with pytest.raises(InvalidInput):
            parse_maps(bad)
    with pytest.raises(InvalidInput, match="role"):
        new_key("root", ("a",), now_s=0.0)
