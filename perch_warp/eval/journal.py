"""Resume state of an evaluation in OUTDIR: the journal (targets.jsonl), results.csv, eval_config.json."""

from __future__ import annotations

import json
import os
import sys
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import bop
from ..bop import Selection, Target
from ..errors import PerchError
from ..outputs import atomic_write_text

CONFIG_FILE = "eval_config.json"


JOURNAL_FILE = "targets.jsonl"


RESULTS_FILE = "results.csv"


# Arguments that choose what to evaluate or where to write, not how to search:
# changing them between runs of one OUTDIR is fine.
NOT_SEARCH_OPTIONS = {
    "out",
    "restart",
    "max_images",
    "scenes",
    "objects",
    "gallery",
    "no_plots",
    "device",
    "func",
    "command",
    "quiet",
    "verbose",
    "progress",
    "top_k",
    "batch_pixels",
    "cpu_threads",  # the scores do not depend on the number of CPU threads
    "max_candidates",  # a guard, not a search setting
    # Where the targets run (Ray workers or this process) does not change the scores: a run may be
    # interrupted and resumed serial or distributed, either way.
    "ray",
    "ray_workers",
    "ray_cpus_per_worker",
}


@dataclass
class Done:
    """A finished target: its estimate, as read back from results.csv or the journal."""

    obj_id: int
    R: np.ndarray
    t_m: np.ndarray
    score: float
    time_s: float
    details: dict = field(default_factory=dict)
    # The search's heat map (perch_warp.score_map.ScoreMap) on the way from the search to its file under
    # heatmaps/; never journalled (None when read back).
    heatmap: object = field(default=None, compare=False, repr=False)


def repair_journal(out_dir: Path) -> None:
    """Cut off a last journal line torn by a crash (no final newline), so that the next record is not
    appended onto it; the cut target's row in results.csv, if written, still counts, else it runs again."""
    path = out_dir / JOURNAL_FILE
    if not path.exists():
        return
    data = path.read_bytes()
    if not data or data.endswith(b"\n"):
        return
    keep = data.rfind(b"\n") + 1
    with open(path, "r+b") as f:
        f.truncate(keep)
        f.flush()
        os.fsync(f.fileno())
    print(
        f"warning: {path} ended in an incomplete line ({len(data) - keep} bytes, left by an interrupted run): "
        "cut off; its target counts only if results.csv has it",
        file=sys.stderr,
    )


def load_state(out_dir: Path, selection: Selection) -> tuple[dict, list[bop.BopResult], dict]:
    """Finished targets keyed (scene, im, inst), results.csv rows that match no current target, and the
    targets whose last journal record is a failure (key -> reason).

    Rows are matched to targets by order: the k-th row of object o in an image is the
    k-th instance of o in scene_gt.json. Per-target times come from the journal; rows
    without a journal line get an equal share of their image's time.
    """
    done: dict[tuple[int, int, int], Done] = {}
    foreign: list[bop.BopResult] = []
    results_path = out_dir / RESULTS_FILE
    if results_path.exists():
        rows = bop.read_results(results_path)
        by_image: dict[tuple[int, int], list[bop.BopResult]] = defaultdict(list)
        for r in rows:
            by_image[(r.scene_id, r.im_id)].append(r)
        insts: dict[tuple[int, int, int], list[int]] = defaultdict(list)
        for t in selection.targets:
            insts[(t.scene_id, t.im_id, t.obj_id)].append(t.inst)
        # Instances of each object in an image, in scene_gt order, are matched to rows in file order.
        for (scene_id, im_id), im_rows in by_image.items():
            used: Counter = Counter()
            for r in im_rows:
                cand = insts.get((scene_id, im_id, r.obj_id), [])
                k = used[r.obj_id]
                used[r.obj_id] += 1
                if k < len(cand):
                    share = r.time_s / len(im_rows) if r.time_s >= 0 else float("nan")
                    done[(scene_id, im_id, cand[k])] = Done(r.obj_id, r.R, r.t_mm / 1000.0, r.score, share)
                else:
                    foreign.append(r)
    failed = _read_journal(out_dir / JOURNAL_FILE, done)
    return done, foreign, failed


def _read_journal(journal: Path, done: dict) -> dict[tuple[int, int, int], str]:
    """Add the journal's finished targets to `done` (a journal line wins over results.csv); returns the
    targets whose last record is a failure (key -> reason)."""
    failed: dict[tuple[int, int, int], str] = {}
    if journal.exists():
        for no, line in enumerate(journal.read_text().splitlines(), start=1):
            if not line.strip():
                continue
            try:
                j = json.loads(line)
                key = (int(j["scene_id"]), int(j["im_id"]), int(j["inst"]))
                if "failed" in j:
                    if key not in done:
                        failed[key] = str(j["failed"])
                    continue
                d = Done(
                    int(j["obj_id"]),
                    np.asarray(j["R"], dtype=np.float64).reshape(3, 3),
                    np.asarray(j["t_mm"], dtype=np.float64).reshape(3) / 1000.0,
                    float(j["score"]),
                    float(j["time_s"]),
                    j.get("details", {}),
                )
            except (ValueError, KeyError, TypeError) as e:
                # Torn tails are cut before a run (repair_journal); this is damage inside the file.
                print(
                    f"warning: {journal} line {no} unreadable ({e}): skipped (its target counts if results.csv "
                    "has it, else it runs again)",
                    file=sys.stderr,
                )
                continue
            done[key] = d
            failed.pop(key, None)
    return failed


def write_results(out_dir: Path, selection: Selection, done: dict, foreign: list[bop.BopResult]) -> None:
    """Rewrite results.csv from the state: per-image time = sum of its targets' times (BOP needs it equal per image)."""
    order = {t.key: i for i, t in enumerate(selection.targets)}
    rows: list[tuple[tuple, bop.BopResult]] = []
    image_time: dict[tuple[int, int], float] = defaultdict(float)
    for key, d in done.items():
        if np.isfinite(d.time_s):
            image_time[key[:2]] += d.time_s
    for r in foreign:
        if r.time_s >= 0:
            image_time[(r.scene_id, r.im_id)] += r.time_s / max(
                1, sum(1 for f in foreign if (f.scene_id, f.im_id) == (r.scene_id, r.im_id))
            )
    for key, d in done.items():
        res = bop.BopResult(key[0], key[1], d.obj_id, d.score, d.R, d.t_m * 1000.0, image_time.get(key[:2], -1.0))
        rows.append(((key[0], key[1], order.get(key, 10**9), key[2]), res))
    for i, r in enumerate(foreign):
        t = image_time.get((r.scene_id, r.im_id), r.time_s)
        rows.append(
            ((r.scene_id, r.im_id, 10**9 + i, 0), bop.BopResult(r.scene_id, r.im_id, r.obj_id, r.score, r.R, r.t_mm, t))
        )
    rows.sort(key=lambda kr: kr[0])
    bop.write_results(out_dir / RESULTS_FILE, [r for _, r in rows])


def append_failure(out_dir: Path, target: Target, reason: str) -> None:
    """Journal a failed target: its key and the one-line reason (it is tried again on a rerun)."""
    record = {"scene_id": target.scene_id, "im_id": target.im_id, "inst": target.inst, "obj_id": target.obj_id}
    _append_line(out_dir, json.dumps({**record, "failed": " ".join(reason.split())}))


def _append_line(out_dir: Path, line: str) -> None:
    with open(out_dir / JOURNAL_FILE, "a") as f:
        f.write(line + "\n")
        f.flush()
        os.fsync(f.fileno())


def append_journal(out_dir: Path, target: Target, d: Done) -> None:
    line = json.dumps(
        {
            "scene_id": target.scene_id,
            "im_id": target.im_id,
            "inst": target.inst,
            "obj_id": target.obj_id,
            "score": d.score,
            "time_s": d.time_s,
            "R": d.R.reshape(9).tolist(),
            "t_mm": (d.t_m * 1000.0).tolist(),
            "details": d.details,
        },
        default=json_default,
    )
    _append_line(out_dir, line)


def json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def check_config(out_dir: Path, config: dict, restart: bool) -> None:
    """Refuse to mix results of different search settings in one OUTDIR."""
    path = out_dir / CONFIG_FILE
    config = json.loads(json.dumps(config, default=json_default))  # tuples vs lists, as read back
    if restart:
        for name in (RESULTS_FILE, JOURNAL_FILE, CONFIG_FILE):
            (out_dir / name).unlink(missing_ok=True)
    elif path.exists() and ((out_dir / RESULTS_FILE).exists() or (out_dir / JOURNAL_FILE).exists()):
        old = bop.read_json(path, "evaluation settings")
        if not isinstance(old, dict):
            raise PerchError(f"{path} is not an evaluation settings file: use another --out, or --restart")
        diffs = _setting_diffs(old, config)
        if diffs:
            raise PerchError(
                f"{out_dir} holds results made with other settings: {'; '.join(diffs)}; "
                "use another --out, or --restart to start over"
            )

    atomic_write_text(path, json.dumps(config, indent=1, default=json_default) + "\n")


def _setting_diffs(old: dict, new: dict) -> list[str]:
    """Changed settings as options, briefly: ["--xy-step 0.01 then, 0.02 now", ...]; options that do not
    change scores (NOT_SEARCH_OPTIONS, e.g. --cpu-threads, also in files written before they were
    ignored) are left out."""

    def flat(c: dict) -> dict:
        out = {k: v for k, v in c.items() if k != "options"}
        out.update({k: v for k, v in (c.get("options") or {}).items() if k not in NOT_SEARCH_OPTIONS})
        return out

    a, b = flat(old), flat(new)

    def short(v) -> str:
        text = json.dumps(v)
        return text if len(text) <= 40 else text[:37] + "..."

    names = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    return [f"--{k.replace('_', '-')} {short(a.get(k))} then, {short(b.get(k))} now" for k in names]
