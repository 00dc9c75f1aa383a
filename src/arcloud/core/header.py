"""The map header: what gives a map's stored data its meaning, stored with the map.

A map's voxel keys are indices at one voxel size; its index cells have one size; its floor votes are
height bins of one size along one up; its label votes are columns in one class order; its boxes are in
one aligned frame; its blobs are in one codec version. Read with other
settings, the same bytes mean something else, silently. So a map carries a ``MapHeader`` written when it is created, and whoever
opens it with ``Params`` checks them against it (``check_header``) and refuses a mismatch by name.

Pure: the stores write and read the record (``MapHeader.to_record``/``from_record``, JSON-ready).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

from arcloud.core.checks import check_finite_number, describe
from arcloud.core.errors import InvalidInput, MapMismatch
from arcloud.core.types import CLASSES, Params, check_param_value

#: The settings a header holds that ``Params`` also holds, compared by ``check_header``.
HEADER_SETTINGS: tuple[str, ...] = ("voxel_size_m", "index_cell_m", "floor_bin_m", "up", "world2aligned")


@dataclass(frozen=True, slots=True)
class MapHeader:
    """The settings a map's stored data was written under (see the module docstring).

    voxel_size_m: voxel keys' size. index_cell_m: spatial index cells' size. floor_bin_m: the height
    bins of objects' floor votes. up: (3,) world up. world2aligned: (4, 4) rows, the frame axis-aligned
    boxes are in (None: the world). classes: the label order of the voxels' votes. codec_version: the
    stores' blob format its blobs are in. created_at_s: when the map was created (Unix seconds; not compared)."""

    voxel_size_m: float
    index_cell_m: float
    floor_bin_m: float
    up: tuple[float, float, float]
    world2aligned: tuple[tuple[float, ...], ...] | None
    classes: tuple[str, ...]
    codec_version: int
    created_at_s: float

    @classmethod
    def from_params(cls, params: Params, codec_version: int, created_at_s: float) -> MapHeader:
        """The header of a map created now under ``params``, stored in ``codec_version``."""
        return cls(
            voxel_size_m=float(params.voxel_size_m),
            index_cell_m=float(params.index_cell_m),
            floor_bin_m=float(params.floor_bin_m),
            up=_xyz(params.up),
            world2aligned=None if params.world2aligned is None else tuple(_floats(row) for row in params.world2aligned),
            classes=CLASSES,
            codec_version=_check_version(codec_version),
            created_at_s=check_finite_number("MapHeader.created_at_s", created_at_s),
        )

    def differences(self, params: Params, codec_version: int | None = None) -> list[tuple[str, object, object]]:
        """(setting, the map's value, ours) for each setting in which ``params`` (and ``codec_version``,
        when given) read this map otherwise than it was written; empty when they agree."""
        if codec_version is None:
            codec_version = self.codec_version
        ours = MapHeader.from_params(params, codec_version, self.created_at_s)
        names = (*HEADER_SETTINGS, "classes", "codec_version")
        return [(name, getattr(self, name), getattr(ours, name)) for name in names if getattr(self, name) != getattr(ours, name)]

    def to_record(self) -> dict[str, object]:
        """The header as JSON-ready values (lists for tuples)."""
        return {
            "voxel_size_m": self.voxel_size_m,
            "index_cell_m": self.index_cell_m,
            "floor_bin_m": self.floor_bin_m,
            "up": list(self.up),
            "world2aligned": None if self.world2aligned is None else [list(row) for row in self.world2aligned],
            "classes": list(self.classes),
            "codec_version": self.codec_version,
            "created_at_s": self.created_at_s,
        }

    @classmethod
    def from_record(cls, record: Mapping[str, object]) -> MapHeader:
        """The header of ``to_record``'s values; ``InvalidInput`` naming the first field that is
        missing or malformed."""
        missing = [name for name in cls.__dataclass_fields__ if name not in record]
        if missing:
            raise InvalidInput(f"MapHeader.{missing[0]}", "a value (the header lacks it)", "nothing")
        up, world2aligned, classes = record["up"], record["world2aligned"], record["classes"]
        up = tuple(up) if isinstance(up, list) else up
        if isinstance(world2aligned, list):
            world2aligned = tuple(tuple(row) if isinstance(row, list) else row for row in world2aligned)
        check_param_value("MapHeader.up", "up", up)
        check_param_value("MapHeader.world2aligned", "transform", world2aligned)
        if not isinstance(classes, list) or not all(isinstance(c, str) for c in classes):
            raise InvalidInput("MapHeader.classes", "a list of class names", describe(classes))
        return cls(
            voxel_size_m=check_finite_number("MapHeader.voxel_size_m", record["voxel_size_m"], positive=True),
            index_cell_m=check_finite_number("MapHeader.index_cell_m", record["index_cell_m"], positive=True),
            floor_bin_m=check_finite_number("MapHeader.floor_bin_m", record["floor_bin_m"], positive=True),
            up=_xyz(up),  # type: ignore[arg-type]  # `up` is object here: check_param_value above held it a 3-tuple of numbers
            world2aligned=None if world2aligned is None else tuple(_floats(row) for row in world2aligned),  # type: ignore[attr-defined]  # checked: rows of numbers
            classes=tuple(classes),
            codec_version=_check_version(record["codec_version"]),
            created_at_s=check_finite_number("MapHeader.created_at_s", record["created_at_s"]),
        )


def check_header(
    header: MapHeader,
    params: Params,
    *,
    codec_version: int | None = None,
    map_id: str | None = None,
) -> None:
    """Refuse to read or write a map under settings other than its own: ``MapMismatch`` naming each
    setting that differs, with the map's value and ours (``codec_version``: ours, when it matters)."""
    differences = header.differences(params, codec_version)
    if differences:
        raise MapMismatch(map_id, differences)


def _floats(values: Iterable[float]) -> tuple[float, ...]:
    return tuple(float(v) for v in values)


def _xyz(values: Sequence[float]) -> tuple[float, float, float]:
    x, y, z = values
    return float(x), float(y), float(z)


def _check_version(value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise InvalidInput("MapHeader.codec_version", "an integer >= 1", describe(value))
    return value


__all__ = ["HEADER_SETTINGS", "MapHeader", "check_header"]
