"""The joint step of a several-object search (perch_warp.joint) against brute force and geometry."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from perch_warp.joint import (
    Peak,
    choose,
    conflict,
    convex_hull_2d,
    footprint,
    footprint_overlap_m,
    height_range,
    hidden_share,
)
from perch_warp.table import Table, rot_z


def brute_force_key(scores, clash):
    """The best (conflicting pairs, -total score) over every combination, enumerated independently."""
    n = len(scores)
    keys = []
    for picks in itertools.product(*(range(len(s)) for s in scores)):
        bad = sum(clash(i, picks[i], j, picks[j]) is not None for i in range(n) for j in range(i + 1, n))
        keys.append((bad, -sum(scores[i][a] for i, a in enumerate(picks))))
    return min(keys)


def random_case(rng, n_obj, max_peaks, p_clash):
    scores = [list(np.round(rng.uniform(0.2, 0.9, rng.integers(1, max_peaks + 1)), 2)) for _ in range(n_obj)]
    table = {
        (i, a, j, b): ("x" if rng.random() < p_clash else None)
        for i in range(n_obj)
        for j in range(i + 1, n_obj)
        for a in range(len(scores[i]))
        for b in range(len(scores[j]))
    }
    return scores, lambda i, a, j, b: table[(i, a, j, b)]


def test_choose_exact_matches_brute_force():
    rng = np.random.default_rng(7)
    for _ in range(300):
        scores, clash = random_case(rng, int(rng.integers(1, 5)), 4, float(rng.uniform(0, 0.8)))
        c = choose(scores, clash)
        assert c.method == "exact"
        assert c.combinations == math.prod(len(s) for s in scores)
        key = (len(c.conflicts), -sum(scores[i][a] for i, a in enumerate(c.picks)))
        assert key[0] == brute_force_key(scores, clash)[0]
        assert key[1] == pytest.approx(brute_force_key(scores, clash)[1], abs=1e-12)
        assert c.total_score == pytest.approx(-key[1])


def test_choose_without_conflicts_takes_each_best():
    rng = np.random.default_rng(1)
    for _ in range(50):
        scores, _ = random_case(rng, int(rng.integers(1, 6)), 5, 0.0)
        for exact_max in (0, 10**9):  # greedy and exact agree when nothing conflicts
            c = choose(scores, lambda *a: None, exact_max=exact_max)
            assert c.picks == [int(np.argmax(s)) for s in scores]
            assert c.conflicts == []


def test_greedy_on_a_known_case():
    # Object 0's best peak (0.9) conflicts with object 1's best (0.8); object 1's second (0.7) is free.
    scores = [[0.9, 0.5], [0.8, 0.7]]
    clashes = {(0, 0, 1, 0)}

    def clash(i, a, j, b):
        return "overlap" if (i, a, j, b) in clashes else None

    greedy = choose(scores, clash, exact_max=0)
    assert greedy.method == "greedy" and greedy.picks == [0, 1] and greedy.conflicts == []
    exact = choose(scores, clash)
    assert exact.method == "exact" and exact.picks == [0, 1]
    # Greedy is not exact: object 0 first takes 0.9, which forces object 1 to 0.1; exactly, 0.85 + 0.8.
    scores = [[0.9, 0.85], [0.8, 0.1]]
    greedy = choose(scores, clash, exact_max=0)
    exact = choose(scores, clash)
    assert greedy.picks == [0, 1] and exact.picks == [1, 0]
    assert exact.total_score > greedy.total_score


def test_greedy_never_adds_an_avoidable_conflict():
    rng = np.random.default_rng(3)
    for _ in range(200):
        scores, clash = random_case(rng, int(rng.integers(2, 6)), 4, 0.3)
        c = choose(scores, clash, exact_max=0)
        order = sorted(range(len(scores)), key=lambda i: -max(scores[i]))
        for pos, i in enumerate(order):
            counts = [n_clash(clash, c.picks, i, a, order[:pos]) for a in range(len(scores[i]))]
            assert counts[c.picks[i]] == min(counts)


def n_clash(clash, picks, i, a, earlier) -> int:
    """Conflicts of object i's peak a with the peaks picked for the objects `earlier`."""
    pairs = ((i, a, j, picks[j]) if i < j else (j, picks[j], i, a) for j in earlier)
    return sum(clash(*p) is not None for p in pairs)


def test_choose_says_why_each_moved_object_left_its_own_best():
    # Object 1's best (0.8) conflicts with object 0's best (0.9) and object 2's best (0.7); object 0 keeps
    # its best, object 2 too (its best is free of the others' picks), object 1 moves to its second peak.
    scores = [[0.9, 0.2], [0.8, 0.75], [0.7, 0.1]]
    clashes = {(0, 0, 1, 0): "overlap", (1, 0, 2, 0): "hidden"}

    def clash(i, a, j, b):
        return clashes.get((i, a, j, b))

    for exact_max in (0, 10**9):
        c = choose(scores, clash, exact_max=exact_max)
        assert c.picks == [0, 1, 0] and c.conflicts == []
        assert c.moved == [(1, 0, "overlap"), (1, 2, "hidden")]
        assert c.moved_by(1) == [(0, "overlap"), (2, "hidden")] and c.moved_by(0) == []
        want = [{"object": 1, "by": 0, "why": "overlap"}, {"object": 1, "by": 2, "why": "hidden"}]
        assert c.to_dict()["moved"] == want
    # Nothing moved: nothing to explain.
    assert choose(scores, lambda *a: None).moved == []


def test_choose_refuses_an_object_without_peaks():
    with pytest.raises(ValueError):
        choose([[0.5], []], lambda *a: None)


def minkowski_depth(a: np.ndarray, b: np.ndarray) -> float:
    """Penetration depth as the distance from the origin to the boundary of the Minkowski difference
    a - b (0 when the origin lies outside): an independent reference for footprint_overlap_m."""
    d = convex_hull_2d((a[:, None, :] - b[None, :, :]).reshape(-1, 2))
    e = np.roll(d, -1, axis=0) - d
    n = np.stack([e[:, 1], -e[:, 0]], 1) / np.linalg.norm(e, axis=1)[:, None]  # outward: hull is CCW
    dist = (d * n).sum(1)  # how far inside each edge (outward normal n) the origin lies
    return float(dist.min()) if (dist > 0).all() else 0.0


def rectangle(cx, cy, w, h, yaw):
    c = np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]])
    R = rot_z(yaw)[:2, :2]
    return c @ R.T + [cx, cy]


def test_footprint_overlap_against_minkowski_difference():
    rng = np.random.default_rng(11)
    for _ in range(300):
        if rng.random() < 0.5:
            a = rectangle(0, 0, *rng.uniform(0.02, 0.2, 2), rng.uniform(0, math.pi))
            b = rectangle(*rng.uniform(-0.15, 0.15, 2), *rng.uniform(0.02, 0.2, 2), rng.uniform(0, math.pi))
        else:
            a = convex_hull_2d(rng.normal(0, 0.05, (8, 2)))
            b = convex_hull_2d(rng.normal(rng.uniform(-0.1, 0.1, 2), 0.05, (8, 2)))
        got, want = footprint_overlap_m(a, b), minkowski_depth(a, b)
        if want > 0:
            assert got == pytest.approx(want, abs=1e-9)
        else:
            assert got <= 1e-9


def test_footprint_overlap_known_squares():
    a = rectangle(0, 0, 0.1, 0.1, 0.0)
    assert footprint_overlap_m(a, rectangle(0.08, 0, 0.1, 0.1, 0.0)) == pytest.approx(0.02)
    assert footprint_overlap_m(a, rectangle(0.0, 0.0, 0.02, 0.02, 0.3)) > 0.05  # one inside the other
    assert footprint_overlap_m(a, rectangle(0.2, 0, 0.1, 0.1, 0.0)) < 0


def test_footprint_of_a_posed_box():
    # A 4 x 2 x 1 cm box posed at (0.1, -0.05) m, yaw 30 deg on a table seen from 0.8 m.
    corners = np.array(list(itertools.product([-0.02, 0.02], [-0.01, 0.01], [-0.005, 0.005])))
    R_t2c = np.diag([1.0, -1.0, -1.0])  # camera looking straight down at the table
    table = Table(R_t2c, np.array([0.0, 0.0, 0.8]))
    yaw = math.radians(30)
    R_m2t, t_m2t = rot_z(yaw), np.array([0.1, -0.05, 0.005])
    T = np.eye(4)
    T[:3, :3] = table.R_t2c @ R_m2t
    T[:3, 3] = table.R_t2c @ t_m2t + table.t_t2c_m
    got = footprint(table, T, corners)
    assert height_range(table, T, corners) == pytest.approx((0.0, 0.01))
    want = rectangle(0.1, -0.05, 0.04, 0.02, yaw)
    assert len(got) == 4
    for p in want:
        assert np.min(np.linalg.norm(got - p, axis=1)) < 1e-9


def test_hidden_share_and_conflict():
    h, w = 40, 60
    near = np.zeros((h, w), bool)
    far = np.zeros((h, w), bool)
    near[10:30, 10:30] = True  # 400 px
    far[10:30, 20:40] = True  # 400 px, 200 of them behind `near`
    assert hidden_share(near, far) == pytest.approx(0.5)
    assert hidden_share(near, np.zeros_like(far)) == 0.0
    apart = [rectangle(0, 0, 0.05, 0.05, 0), rectangle(0.2, 0, 0.05, 0.05, 0)]
    p = Peak(0.8, apart[0], near, 0.7)
    q = Peak(0.6, apart[1], far, 0.9)
    assert conflict(p, q, alpha=0.5) is None  # exactly half hidden: the top-α mean still sees its own half
    assert conflict(p, q, alpha=0.6) == "the farther is 50 % hidden behind the nearer (more than 1 - alpha)"
    # The nearer object is the one hidden when the distances swap: near's 400 px, 200 behind far.
    q_near = Peak(0.6, apart[1], far, 0.5)
    assert conflict(p, q_near, alpha=0.5) is None
    touching = Peak(0.6, rectangle(0.045, 0, 0.05, 0.05, 0), np.zeros((h, w), bool), 0.9)
    assert conflict(p, touching, alpha=0.5) is None  # 5 mm overlap: within the 1 cm tolerance
    overlapping = Peak(0.6, rectangle(0.02, 0, 0.05, 0.05, 0), np.zeros((h, w), bool), 0.9)
    assert "footprints overlap by 3.0 cm" == conflict(p, overlapping, alpha=0.5)
    # Stacked: the same footprint, but one stands on the other (heights 0-4 cm and 4-12 cm): no conflict.
    low = Peak(0.8, apart[0], np.zeros((h, w), bool), 0.7, (0.0, 0.04))
    high = Peak(0.6, rectangle(0.01, 0, 0.05, 0.05, 0), np.zeros((h, w), bool), 0.9, (0.04, 0.12))
    assert conflict(low, high, alpha=0.5) is None
    assert "footprints overlap" in conflict(low, dataclasses.replace(high, z_m=(0.02, 0.10)), alpha=0.5)
