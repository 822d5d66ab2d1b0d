"""Scores already known: a search's plain scores (and silhouette bounds) kept by pose, so that a second
search of the same photo takes them instead of scoring (or bounding) those candidates again.

The several-object search's second pass (perch_warp.objects, `occluders="answers"`) searches each object
again with the others' answers hiding what they cover (perch_warp.hidden). A candidate none of whose
feature points an answer can hide scores exactly as in the first pass: the same photo (features and
rarity), the same render, and with no point hidden the reduction is the plain top-α mean bit for bit
(kernels/reduce.py); its silhouette bound (perch_warp.bound, marked the same way) is the first pass's
too. Only the candidates whose feature-grid boxes reach behind another answer are scored and bounded
anew (`HiddenPoints.untouched` decides, conservatively), so the second pass visits, rules out and
answers as a pass that computes everything would, and costs what its touched candidates cost.

What is kept is the value before the place's own term (the footing prior, added per call), per kind
("score" or "bound") and scoring setting: the score's terms (the grid stage and the refinement score
differently), the renderer and the engine's configuration; one KnownScores serves one object (engine)
in one photo.
"""

from __future__ import annotations

import numpy as np

from ..errors import PerchError


class KnownScores:
    """Plain scores and bounds of one object's candidates in one photo, by camera-frame pose (R, t bit for
    bit). `counts`: the scores and bounds kept, and those taken instead of computed. Host memory: about
    200 bytes per kept value (a search of millions of candidates keeps hundreds of megabytes)."""

    def __init__(self, photo) -> None:
        self.photo = photo  # search.scoring.Photo: the scores hold for this photo only
        self._tables: dict[tuple, dict[bytes, float]] = {}
        self.counts = dict.fromkeys(("scores_reused", "scores_kept", "bounds_reused", "bounds_kept"), 0)

    def _table(self, service, kind: str) -> dict[bytes, float]:
        if service.photo is not self.photo:
            raise PerchError("known scores are of another photo: make one KnownScores per object and photo")
        if kind not in ("score", "bound"):
            raise PerchError(f"known values are scores or bounds, not {kind!r}")
        return self._tables.setdefault((kind, service.renderer, service.terms, service.config), {})

    def take(self, service, kind: str, R: np.ndarray, t: np.ndarray, out: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """out[i] = the known value (`kind` "score" or "bound") of candidate i (pose R[i], t[i]) for each i
        of idx known under the service's setting; returns (len(idx),) bool: which were (the rest must be
        computed)."""
        table = self._table(service, kind)
        if not table or len(idx) == 0:
            return np.zeros(len(idx), dtype=bool)
        got = [table.get(k) for k in _keys(R[idx], t[idx])]
        hit = np.fromiter((g is not None for g in got), dtype=bool, count=len(got))
        out[idx[hit]] = [g for g in got if g is not None]
        self.counts[f"{kind}s_reused"] += int(hit.sum())
        return hit

    def keep(self, service, kind: str, R: np.ndarray, t: np.ndarray, values: np.ndarray, idx: np.ndarray) -> None:
        """Keep values[i] as the plain value (`kind`) of candidate i (pose R[i], t[i]) for each i of idx."""
        if len(idx) == 0:
            return
        table = self._table(service, kind)
        table.update(zip(_keys(R[idx], t[idx]), values[idx].tolist(), strict=True))
        self.counts[f"{kind}s_kept"] += len(idx)

    def to_dict(self) -> dict:
        return dict(self.counts)


def _keys(R: np.ndarray, t: np.ndarray) -> list[bytes]:
    """One key per pose: its rotation's and translation's float64 bits (the same grid point, set up the
    same way, gives the same bits in both passes)."""
    n = len(t)
    rows = np.ascontiguousarray(np.concatenate([R.reshape(n, 9), t.reshape(n, 3)], axis=1), dtype=np.float64)
    return rows.view(np.dtype((np.void, rows.itemsize * 12))).ravel().tolist()
