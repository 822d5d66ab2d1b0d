"""The exhaustive search: every candidate of the space scored."""

from __future__ import annotations

from ..search_space import SearchSpace
from .base import Outcome
from .scoring import PoseSource, ScoringService, SearchStats


def run(service: ScoringService, space: SearchSpace) -> Outcome:
    """Every grid candidate's score (-inf where it shows no feature point)."""
    stats = SearchStats()
    scores = service.score(PoseSource.of_space(space), stats)
    return Outcome(scores, len(space), stats)
