"""The throughput model of benchmarks/session.py (workers/throughput.py): fit and prediction arithmetic."""

from __future__ import annotations

import heapq

import pytest

from schlieren.pipeline.stages import STAGES
from schlieren.workers import throughput as tp
from schlieren.workers.plan import Extents, critical_path_priorities, make_plan

# known seconds per index of each stage
COST = {"sync": 0.05, "clock": 0.01, "capture": 0.02, "deflection": 0.2, "resample": 0.1, "potential": 0.1,
        "mask": 0.1, "geometry": 10.0, "hull": 1.0, "integrate": 0.5, "regularisation": 0.5}
COLD, WARM, PER_SUMMARY = 3.0, 2.0, 0.001


def synthetic_receipts(cameras: int, frames: int, *, block: int = 4, margin: int = 2, noise: float = 0.0):
    """One receipt per index of every stage of a cameras x frames run, with the known costs
    (``noise`` alternately added and subtracted where a stage has several receipts; an even
    count per stage keeps the means)."""
    out = []
    sign = 1.0

    def add(stage, index, seconds):
        nonlocal sign
        sign = -sign
        jitter = 0.0 if stage in ("clock", "geometry", "threshold", "regularisation") else sign * noise  # one each
        out.append({"stage": stage, "index": list(index), "seconds": seconds + jitter,
                    "cpu_seconds": 0.5 * seconds, "skipped": False})

    for c in range(cameras):
        add("sync", (c,), COST["sync"])
        for k in range(frames):
            for s in ("resample", "potential", "mask"):
                add(s, (c, k), COST[s])
        for j in range(frames + 2 * margin):
            add("deflection", (c, j), COST["deflection"])
    for c in range(cameras):  # apart from the loop above, whose even count per camera would give sync one sign
        add("capture", (c,), COST["capture"])
    add("clock", (), COST["clock"])
    add("geometry", (), COST["geometry"])
    add("threshold", (), PER_SUMMARY * cameras * frames)
    add("regularisation", (), COST["regularisation"])
    for k in range(frames):
        add("hull", (k,), COST["hull"])
        add("tomography", (k,), COLD if k % block == 0 else WARM)
        add("integrate", (k,), COST["integrate"])
    # a skipped receipt (resumed run) must not count
    out.append({"stage": "tomography", "index": [1], "seconds": 99.0, "cpu_seconds": 0.0, "skipped": True})
    return out


def test_phases_cover_every_stage():
    assert sorted(tp.PHASE_A + (tp.BARRIER,) + tp.PHASE_C) == sorted(s.name for s in STAGES)


def test_fit_recovers_known_costs():
    costs = tp.fit_costs(synthetic_receipts(2, 8, noise=0.01), cameras=2, frames=8, warm_start_block=4)
    for s, v in COST.items():
        assert costs.per_index[s] == pytest.approx(v, abs=1e-3), s
    assert costs.tomography_cold == pytest.approx(COLD, abs=1e-2)
    assert costs.tomography_warm == pytest.approx(WARM, abs=1e-2)
    assert costs.threshold_per_summary == pytest.approx(PER_SUMMARY, abs=1e-3)
    assert costs.source["receipts"] == len(synthetic_receipts(2, 8)) - 1
    cpu = tp.fit_costs(synthetic_receipts(2, 8), cameras=2, frames=8, field_name="cpu_seconds")
    assert cpu.per_index["hull"] == pytest.approx(0.5 * COST["hull"])


def test_fit_refuses_an_incomplete_run():
    rs = [r for r in synthetic_receipts(2, 4) if r["stage"] != "threshold"]
    with pytest.raises(ValueError, match="threshold"):
        tp.fit_costs(rs, cameras=2, frames=4)


def test_task_counts():
    n = tp.task_counts(16, 1000, raw_margin=2, frames_per_task=1)
    assert n["deflection"] == 16 * 1004 and n["mask"] == 16000 and n["tomography"] == 1000
    assert n["threshold"] == n["clock"] == n["geometry"] == n["regularisation"] == 1
    assert n["sync"] == n["capture"] == 16
    assert sum(n.values()) == 67100
    b = tp.task_counts(8, 16, raw_margin=2, frames_per_task=8)
    assert b["resample"] == 8 * 2 and b["deflection"] == 8 * 3 and b["hull"] == 16


def test_prediction_by_hand():
    """16 cameras x 1000 frames on 8 workers, worked out term by term."""
    costs = tp.fit_costs(synthetic_receipts(2, 8), cameras=2, frames=8).with_overheads(0.005, 0.0)
    p = tp.predict(costs, cameras=16, frames=1000, workers=8, warm_start_block=4, raw_margin=2)
    W_A = 16 * 0.05 + 0.01 + 16 * 0.02 + 16 * 1004 * 0.2 + 16000 * 0.1 + 16000 * 0.1 + 10.0  # 6423.93
    W_C = 16000 * 0.1 + 0.5 + 1000 * 1.0 + (250 * 3.0 + 750 * 2.0) + 1000 * 0.5  # 5350.5
    L_A = max(0.05 + 0.01, 0.02 + 0.2) + 0.1 + 0.1
    L_C = 0.1 + max(1.0, 0.5) + 3.0 + 3 * 2.0 + 0.5   # mask, hull or regularisation, solves, integrate
    T_B = 16000 * 0.001
    overhead = 0.005 * (67100 / 8 + 12)
    assert p.seconds == pytest.approx(W_A / 8 + W_C / 8 + (1 - 1 / 8) * (L_A + L_C) + T_B + overhead)
    assert p.seconds == pytest.approx(1497.44625 + 0.005 * (67100 / 8 + 12))
    W_A_needed = W_A - 10.0  # the geometry may run after the barrier
    # here the phases bind: the barrier's wait (T_B) is more than the geometry's share of the work
    assert W_A_needed / 8 + T_B + W_C / 8 > (W_A + T_B + W_C) / 8
    assert p.lower == pytest.approx(W_A_needed / 8 + T_B + W_C / 8)
    assert p.tasks == 67100
    assert p.limiting == "deflection: work / N"
    assert p.terms["geometry wait"] == 0.0
    assert sum(v for k, v in p.terms.items() if "not added" not in k) == pytest.approx(p.seconds)
    # planning happens once, before any task: added as it is, to the bound too
    q = tp.predict(costs, cameras=16, frames=1000, workers=8, planning=100.0)
    assert q.seconds == pytest.approx(p.seconds + 100.0) and q.lower == pytest.approx(p.lower + 100.0)


def test_limiting_terms():
    base = tp.fit_costs(synthetic_receipts(2, 8), cameras=2, frames=8)
    # one scheduler for ~67k tasks at 5 ms each outlasts 128 workers' share of the work
    p = tp.predict(base.with_overheads(0.0, 0.005), cameras=16, frames=1000, workers=128)
    assert p.limiting.startswith("scheduler throughput") and p.seconds == pytest.approx(0.005 * 67100)
    q = tp.predict(base.with_overheads(0.0, 0.005), cameras=16, frames=1000, workers=128, planning=1000.0)
    assert q.limiting.startswith("planning") and q.seconds == pytest.approx(1000.0 + 0.005 * 67100)
    # a slow barrier dominates once the work is spread thin
    slow = tp.StageCosts(per_index=base.per_index, tomography_cold=COLD, tomography_warm=WARM,
                         threshold_per_summary=0.01)
    assert tp.predict(slow, cameras=16, frames=1000, workers=128).limiting.startswith("threshold barrier")
    # few frames on many workers: the chain of one warm-start block
    chain = tp.predict(base, cameras=1, frames=8, workers=64)
    assert chain.limiting.startswith("warm-start chain")
    # a short run: the single geometry task outlasts everything before the solves
    geo = tp.predict(base, cameras=1, frames=1, workers=4)
    W_A = 0.05 + 0.01 + 0.02 + 5 * 0.2 + 0.1 + 0.1 + 10.0  # phase A's work / 4 outlasts its chain
    assert geo.terms["geometry wait"] == pytest.approx(10.0 - W_A / 4 - 0.001 - 0.1 - 1.0)


def test_ready_gaps():
    deps = {"b": ("a",), "c": (), "d": ("x",)}
    spans = [("a", "w1", 0.0, 1.0), ("b", "w1", 1.25, 2.0),  # b was ready when a stopped: gap 0.25
             ("x", "w2", 0.0, 3.0), ("c", "w1", 2.5, 3.0),  # c had no deps: gap 0.5
             ("d", "w1", 3.5, 4.0)]  # d waited for x (stopped 3.0 = c's stop): gap 0.5 counts
    assert sorted(tp.ready_gaps(spans, deps)) == [0.25, 0.5, 0.5]
    late = [("a", "w1", 0.0, 1.0), ("x", "w2", 0.0, 2.0), ("d", "w1", 2.1, 3.0)]
    assert tp.ready_gaps(late, deps) == []  # d became ready only at 2.0: the graph's idle time


def _simulate(plan, seconds, workers):
    """Greedy list schedule of ``plan`` on ``workers`` (highest critical-path rank first)."""
    rank = critical_path_priorities(plan, costs=COST | {"tomography": WARM, "threshold": 0.1})
    waiting = {t.key: set(t.deps) for t in plan.tasks}
    users: dict[str, list[str]] = {t.key: [] for t in plan.tasks}
    for t in plan.tasks:
        for d in t.deps:
            users[d].append(t.key)
    ready = [(-rank[k], k) for k, d in waiting.items() if not d]
    heapq.heapify(ready)
    running: list[tuple[float, str]] = []
    now, free = 0.0, workers
    while ready or running:
        while free and ready:
            _, k = heapq.heappop(ready)
            heapq.heappush(running, (now + seconds[k], k))
            free -= 1
        now, k = heapq.heappop(running)
        free += 1
        for u in users[k]:
            waiting[u].discard(k)
            if not waiting[u]:
                heapq.heappush(ready, (-rank[u], u))
    return now


@pytest.mark.parametrize("workers", [1, 2, 3, 8, 40])
def test_bounds_hold_on_the_real_plan(workers):
    """A greedy schedule of the plan's real task graph lies between the model's bounds."""
    C, F, B, m = 3, 10, 4, 2
    plan = make_plan(Extents(camera=C, frame=F, raw_frame=F + 2 * m, raw_offset=m, warm_start_block=B), "t")
    costs = tp.fit_costs(synthetic_receipts(C, F, block=B, margin=m), cameras=C, frames=F, warm_start_block=B)

    def task_seconds(t):
        if t.stage == "tomography":
            return COLD if t.index[0] % B == 0 else WARM
        if t.stage == "threshold":
            return PER_SUMMARY * C * F
        return COST[t.stage] * len(t.indices)

    sim = _simulate(plan, {t.key: task_seconds(t) for t in plan.tasks}, workers)
    p = tp.predict(costs, cameras=C, frames=F, workers=workers, warm_start_block=B, raw_margin=m)
    assert p.lower - 1e-9 <= sim <= p.seconds + 1e-9
    if workers == 40:  # plenty of workers: the geometry task and one block's chain are the run
        assert p.lower == pytest.approx(COST["geometry"] + COST["regularisation"] + COLD + (B - 1) * WARM
                                        + COST["integrate"])
        assert sim == pytest.approx(p.lower)
    if workers == 1:  # one worker: the sum of all work, whatever the order
        total = sum(task_seconds(t) for t in plan.tasks)
        assert sim == pytest.approx(total)
        assert p.seconds == pytest.approx(total) and p.lower == pytest.approx(total)
