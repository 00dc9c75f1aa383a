"""What one store call may write of the spatial index: cells of ``Params.index_cell_m`` (a map's header says
its size), counted before they are listed.

Redis writes an object's index cells (one SET each) inside one Lua script, and Redis runs nothing else while a
script runs: a snapshot holding 50 objects of 100 000 cells each held it 15.9 s, and deleting that map 9.0 s
again. So every write is bounded here, for every store: an object covers at most ``MAX_OBJECT_CELLS`` cells (the
cells one space claim takes, ``MAX_CELLS_PER_CALL``: a 16 m cube of 1 m cells, far beyond any object in a room),
one script adds and removes at most ``MAX_SCRIPT_CELLS`` (an object rewritten at its largest: its old cells
out, its new ones in; about 25 ms of Redis), and one lock call takes at most ``MAX_LOCKS_PER_CALL`` objects.
"""

from __future__ import annotations

import math

import numpy as np

from arcloud.core.ports import MAX_CELLS_PER_CALL
from arcloud.errors import InvalidInput, TooManyCells

#: The most index cells an object's bounds may cover (a commit or a restore of a larger one is refused).
MAX_OBJECT_CELLS = MAX_CELLS_PER_CALL
#: The most index cells one write (one Redis script) adds and removes together.
MAX_SCRIPT_CELLS = 2 * MAX_OBJECT_CELLS
#: The most objects one lock call takes (one key each, in one script).
MAX_LOCKS_PER_CALL = MAX_CELLS_PER_CALL


def count_cells(lo: np.ndarray, hi: np.ndarray, cell_m: float) -> float:
    """How many index cells of ``cell_m`` the box [lo, hi] (each (3,), metres) touches; inf when unbounded, a float
    so that a huge box never overflows."""
    with np.errstate(invalid="ignore", over="ignore"):
        c_lo = np.floor(np.asarray(lo, np.float64) / cell_m)
        c_hi = np.floor(np.asarray(hi, np.float64) / cell_m)
        n_cells = float(np.prod(np.maximum(0.0, c_hi - c_lo + 1)))
    return n_cells if np.isfinite(n_cells) else math.inf


def check_object_cells(field: str, lo: np.ndarray, hi: np.ndarray, cell_m: float) -> int:
    """How many index cells an object of bounds [lo, hi] covers; ``InvalidInput`` naming ``field`` when more than
    ``MAX_OBJECT_CELLS`` (stray far voxels, or a crafted object)."""
    n_cells = count_cells(lo, hi, cell_m)
    if n_cells > MAX_OBJECT_CELLS:
        raise InvalidInput(
            field,
            f"bounds of at most {MAX_OBJECT_CELLS} index cells of {cell_m:g} m",
            f"{n_cells:.0f} cells ({np.round(lo, 3).tolist()} to {np.round(hi, 3).tolist()})",
        )
    return int(n_cells)


def check_script_cells(n_cells: int) -> None:
    """``TooManyCells`` (field ``commit``) when one write would add and remove more than ``MAX_SCRIPT_CELLS``."""
    if n_cells > MAX_SCRIPT_CELLS:
        raise TooManyCells("commit", n_cells, MAX_SCRIPT_CELLS)


def check_lock_ids(n_ids: int) -> None:
    """``InvalidInput`` (field ``ids``) when one lock call would take more than ``MAX_LOCKS_PER_CALL`` objects."""
    if n_ids > MAX_LOCKS_PER_CALL:
        raise InvalidInput("ids", f"at most {MAX_LOCKS_PER_CALL} objects locked in one call", f"{n_ids} objects")


__all__ = [
    "MAX_LOCKS_PER_CALL",
    "MAX_OBJECT_CELLS",
    "MAX_SCRIPT_CELLS",
    "check_lock_ids",
    "check_object_cells",
    "check_script_cells",
    "count_cells",
]
