"""When an object is *confirmed*: served to clients by default. Tentative objects are kept and fused
like any other, but only shown when asked for; a confirmed object whose evidence weakens becomes
tentative again (the rule is re-evaluated at every refinement)."""

from __future__ import annotations

from arcloud.core.types import MapObject, Params


def is_confirmed(obj: MapObject, params: Params) -> bool:
    """Whether a refined object has the evidence to be served."""
    return obj.n_frames >= params.confirm_min_frames and obj.score >= params.confirm_min_score
