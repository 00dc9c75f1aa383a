"""API keys in a JSON file, for the embedded service (``serve --keys-file FILE``) and ``arcloud keys --file``.

The file holds ``{"keys": [record, ...]}`` (``ApiKey.to_record``: the secrets' SHA-256, never a secret),
created with mode 0600. Writers take an exclusive ``flock`` on ``FILE.lock`` and replace the file
atomically (write a temporary file, ``os.replace``), so readers never see half a file and two ``keys
create`` at once both land. Readers re-read the file when its modification time or size changed: a key
created or revoked by the CLI takes effect at the service's next request.
"""

from __future__ import annotations

import fcntl
import json
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from arcloud.access import ApiKey
from arcloud.errors import InvalidInput, StoreError


class FileKeyStore:
    """``KeyStore`` in one JSON file (missing: no keys yet)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self._seen: tuple[int, int] | None = None  # (mtime_ns, size) of the file last read
        self._keys: dict[str, ApiKey] = {}

    def close(self) -> None:
        return None

    def _read(self) -> dict[str, ApiKey]:
        """The file's keys (cached until the file changes)."""
        try:
            stat = self.path.stat()
        except FileNotFoundError:
            return {}
        with self._lock:
            if self._seen != (stat.st_mtime_ns, stat.st_size):
                try:
                    records = json.loads(self.path.read_text())["keys"]
                    keys = {k.id: k for k in (ApiKey.from_record(r) for r in records)}
                except (OSError, ValueError, KeyError, TypeError, InvalidInput) as exc:
                    raise StoreError(f"cannot read the keys file {self.path}: {exc}") from exc
                self._keys, self._seen = keys, (stat.st_mtime_ns, stat.st_size)
            return self._keys

    @contextmanager
    def _writing(self) -> Iterator[dict[str, ApiKey]]:
        """The keys to change, written back atomically under the file lock."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(f"{self.path}.lock", "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            keys = dict(self._read())
            yield keys
            temporary = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
            descriptor = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(descriptor, "w") as out:
                json.dump({"keys": [k.to_record() for k in keys.values()]}, out, indent=1)
                out.flush()
                os.fsync(out.fileno())
            os.replace(temporary, self.path)

    def add(self, key: ApiKey) -> None:
        with self._writing() as keys:
            keys[key.id] = key

    def find(self, key_id: str) -> ApiKey | None:
        return self._read().get(key_id)

    def list_keys(self) -> list[ApiKey]:
        return sorted(self._read().values(), key=lambda k: (k.created_at_s, k.id))

    def count_keys(self) -> int:
        return len(self._read())

    def revoke(self, key_id: str) -> bool:
        with self._writing() as keys:
            return keys.pop(key_id, None) is not None
