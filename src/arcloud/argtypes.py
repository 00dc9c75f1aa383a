"""Argument types shared by every `arcloud` command: each says what it expected when a value is wrong."""

from __future__ import annotations

import argparse
import json
import os
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from arcloud.core.types import Params

#: The environment variable holding ``Params`` overrides (JSON) for every command.
PARAMS_ENV = "ARCLOUD_PARAMS"


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


PARAMS_HELP = (
    "algorithm settings as a JSON object, e.g. '{\"voxel_size_m\": 0.04}' (arcloud.core.types.Params; "
    "default $ARCLOUD_PARAMS or none)"
)


def params_overrides(text: str) -> dict[str, Any]:
    """``--params``: a JSON object of ``Params`` fields (checked when the command builds its ``Params``)."""
    try:
        value = json.loads(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected a JSON object like {{"voxel_size_m": 0.04}}, got {text!r}') from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f'expected a JSON object like {{"voxel_size_m": 0.04}}, got {text!r}')
    return value


def params_from_environment() -> dict[str, Any]:
    """``$ARCLOUD_PARAMS`` as ``params_overrides`` reads it (empty when unset), so that ``demo``, ``eval``,
    ``serve`` and ``worker`` take the same settings the same way."""
    text = os.environ.get(PARAMS_ENV, "").strip()
    if not text:
        return {}
    try:
        return params_overrides(text)
    except argparse.ArgumentTypeError as exc:
        from arcloud.core.errors import InvalidInput

        raise InvalidInput(PARAMS_ENV, 'a JSON object like {"voxel_size_m": 0.04}', repr(text)) from exc


def params_given(overrides: dict[str, Any] | None) -> Params:
    """The command's ``Params``: ``--params`` if given, else ``$ARCLOUD_PARAMS``, read by
    ``core.types.params_from_json`` as the service reads its ``params`` setting."""
    from arcloud.core.types import params_from_json

    return params_from_json(overrides if overrides is not None else params_from_environment())
