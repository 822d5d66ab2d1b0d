"""Searches over the per-photo scoring service (scoring.py), one module each, chosen by name.

A search is a function run(service, space) -> base.Outcome; add one by writing its module and
naming it in SEARCHES. The refinement and probe (refine.py) run after any of them.
"""

from __future__ import annotations

from . import exhaustive, pruned, pyramid
from .base import Outcome, auto_search
from .scoring import PoseSource, ScoringService, SearchStats

SEARCHES = {
    "exhaustive": exhaustive.run,
    "pruned": pruned.run,
    "coarse-to-fine": pyramid.run,
}


def get(name: str):
    """The search called `name` (a key of SEARCHES)."""
    return SEARCHES[name]


__all__ = ["SEARCHES", "Outcome", "PoseSource", "ScoringService", "SearchStats", "auto_search", "get"]
