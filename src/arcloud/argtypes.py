"""Argument types shared by every `arcloud` command: each says what it expected when a value is wrong."""

from __future__ import annotations

import argparse


def int_at_least(text: str, minimum: int) -> int:
    """``text`` as an integer >= ``minimum``, or an argparse error that says so."""
    try:
        value = int(text)
    except ValueError:
        value = minimum - 1
    if value < minimum:
        raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {text!r}")
    return value


def non_negative_int(text: str) -> int:
    return int_at_least(text, 0)


def positive_int(text: str) -> int:
    return int_at_least(text, 1)


def parse_users(text: str) -> tuple[int, ...]:
    """Comma-separated user counts, e.g. ``10,50,100``."""
    try:
        users = tuple(int(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated user counts like 10,50,100, got {text!r}") from None
    if not users or min(users) < 1:
        raise argparse.ArgumentTypeError(f"expected user counts >= 1, got {text!r}")
    return users
