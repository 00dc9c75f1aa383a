"""``arcloud keys create | list | revoke``: the API keys of a service (``arcloud.access``).

    arcloud keys create --redis redis://127.0.0.1:6379/0 --maps office,lab --role device --name "tablet 7"
    arcloud keys list --redis redis://127.0.0.1:6379/0
    arcloud keys revoke --redis redis://127.0.0.1:6379/0 3f9c0a51be27
    arcloud keys create --file keys.json --maps '*' --role admin        # the embedded service's keys file

``create`` prints the token once, on stdout alone (``TOKEN=$(arcloud keys create ...)``); only its SHA-256
is stored. The keys live where the service reads them: ``--file`` (``serve --keys-file``) or ``--redis``
(default ``$ARCLOUD_KEYS_FILE``, else ``$ARCLOUD_STORE`` when it is a Redis URL).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import TYPE_CHECKING

from arcloud.access import ROLES, new_key, parse_maps
from arcloud.errors import ArcloudError, InvalidInput

if TYPE_CHECKING:
    from arcloud.ports import KeyStore


def add_keys_commands(subparsers: argparse._SubParsersAction) -> None:
    keys = subparsers.add_parser(
        "keys",
        help="create, list and revoke the service's API keys",
        description="API keys: each has a role (device: upload frames and read; reader: read; admin: everything, "
        "deleting maps included) on some maps or '*'. Stored hashed, in Redis or in a keys file.",
    )
    actions = keys.add_subparsers(dest="keys_command", required=True)
    create = actions.add_parser("create", help="create a key; prints its token once")
    _where(create)
    create.add_argument("--maps", required=True, help="comma-separated map ids, or '*' for every map")
    create.add_argument("--role", required=True, choices=ROLES, help="device, reader or admin")
    create.add_argument("--name", default="", help="a note to recognise the key by in `keys list`")
    create.set_defaults(handler=run_create)
    listing = actions.add_parser("list", help="list the keys (never their tokens)")
    _where(listing)
    listing.set_defaults(handler=run_list)
    revoke = actions.add_parser("revoke", help="revoke a key: its token stops working within seconds")
    _where(revoke)
    revoke.add_argument("key_id", metavar="ID", help="the key's id (from `keys list`)")
    revoke.set_defaults(handler=run_revoke)


def _where(parser: argparse.ArgumentParser) -> None:
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--redis", metavar="URL", help="the keys in this Redis (default $ARCLOUD_STORE)")
    where.add_argument("--file", metavar="PATH", help="the keys in this file (default $ARCLOUD_KEYS_FILE)")


def open_key_store(args: argparse.Namespace) -> KeyStore:
    """The key store the options (else the environment) name."""
    path = args.file or (None if args.redis else os.environ.get("ARCLOUD_KEYS_FILE"))
    if path:
        from arcloud.stores.file_api_keys import FileKeyStore

        return FileKeyStore(path)
    url = args.redis or os.environ.get("ARCLOUD_STORE", "")
    if not url.startswith(("redis://", "rediss://", "unix://", "redis+cluster://", "rediss+cluster://")):
        raise InvalidInput("--redis", "a Redis URL, or --file PATH (or $ARCLOUD_STORE, $ARCLOUD_KEYS_FILE)", repr(url or None))
    from arcloud.stores.redis_api_keys import RedisKeyStore

    return RedisKeyStore(url)


def run_create(args: argparse.Namespace) -> int:
    key, token = new_key(args.role, parse_maps(args.maps), now_s=time.time(), name=args.name)
    store = open_key_store(args)
    try:
        store.add(key)
    finally:
        store.close()
    print(f"created key {key.id}: {key.role} on {','.join(key.maps)}; the token below is shown once", file=sys.stderr)
    print(token)
    return 0


def run_list(args: argparse.Namespace) -> int:
    store = open_key_store(args)
    try:
        keys = store.list_keys()
    finally:
        store.close()
    print(f"{'ID':<12}  {'ROLE':<6}  {'CREATED (UTC)':<19}  {'MAPS':<30}  NAME")
    for key in keys:
        created = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(key.created_at_s))
        print(f"{key.id:<12}  {key.role:<6}  {created:<19}  {','.join(key.maps):<30}  {key.name}")
    return 0


def run_revoke(args: argparse.Namespace) -> int:
    store = open_key_store(args)
    try:
        revoked = store.revoke(args.key_id)
        left = store.count_keys()
    finally:
        store.close()
    if not revoked:
        raise ArcloudError(f"no key {args.key_id!r} (see `arcloud keys list`)")
    print(f"revoked key {args.key_id}")
    if not left:
        print(
            "arcloud: warning: that was the last key: every request now answers 401 and /readyz 503 (keys: lost) until "
            "`arcloud keys create` makes one",
            file=sys.stderr,
        )
    return 0
