"""The exceptions arcloud raises (defined in ``arcloud.core.errors``, which the core raises too)."""

from arcloud.core.errors import (
    ArcloudError,
    DatasetError,
    FrameGivenUp,
    InvalidInput,
    LockTimeout,
    MapMismatch,
    ModelError,
    StaleLease,
    StoreError,
    StoreUnavailable,
    TooManyCells,
)

__all__ = [
    "ArcloudError",
    "DatasetError",
    "FrameGivenUp",
    "InvalidInput",
    "LockTimeout",
    "MapMismatch",
    "ModelError",
    "StaleLease",
    "StoreError",
    "StoreUnavailable",
    "TooManyCells",
]
