"""The machine-ceiling probe of benchmarks/bench_scale.py (benchmarks/machine_ceiling.py).

Run on tiny arrays for a fraction of a second: the probe starts its processes, they run
single-threaded, and the record has the fields bench_scale.py reads, with values that
follow from their definitions. The ceilings themselves are the machine's, not tested.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import machine_ceiling  # noqa: E402

TINY = {"compute": 32, "warp": 64, "fft": 64, "stream": 64}


@pytest.fixture(scope="module")
def doc() -> dict:
    return machine_ceiling.probe(seconds=0.2, sizes=TINY)


def test_probe_fields_sane(doc):
    assert set(doc["ceilings"]) == set(machine_ceiling.WORKLOADS)
    for name, w in doc["workloads"].items():
        assert w["size"] == TINY[name]
        assert [w[k]["processes"] for k in ("alone_before", "pair", "alone_after")] == [1, 2, 1]
        for key in ("alone_before", "pair", "alone_after"):
            ph = w[key]
            assert all(r >= 1 for r in ph["reps"])
            # each process ran at least the asked wall time (whole repetitions, then stop)
            assert all(s >= 0.2 for s in ph["seconds"])
            pairs = zip(ph["cpu_s"], ph["seconds"], strict=True)
            assert all(0 < c <= s * 1.5 + 0.05 for c, s in pairs)
            assert ph["steal_fraction"] is None or 0 <= ph["steal_fraction"] <= 1
        # the ceiling is the pair's summed throughput over the alone phases' mean
        tp = [sum(r / s for r, s in zip(w[k]["reps"], w[k]["seconds"], strict=True))
              for k in ("alone_before", "pair", "alone_after")]
        assert w["speedup"] == pytest.approx(tp[1] / ((tp[0] + tp[2]) / 2), rel=2e-3)
        assert doc["ceilings"][name] == w["speedup"]
        # No upper bound on the ratio itself: on 0.2 s runs a descheduled alone phase
        # pushes it past 2 (2.73 seen on a noisy VM), and the ceilings are the machine's,
        # not this test's. What cannot vary is that the pair never got more CPUs than exist.
        assert 0 < w["speedup"] < float("inf")
        assert 0 < w["ceiling_two_cores"] == pytest.approx(2 * w["cpu_efficiency"], abs=2e-3)
        assert 0 < doc["cores_used"][name]["pair"] <= os.cpu_count() + 0.2
        assert isinstance(w["quiet"], bool)
        assert w["corun_reps"] >= 0 and "spans" not in w["pair"]
        # the co-run ceiling is timed too (3.13 seen in CI on 0.2 s runs): positive, no bound
        assert w["corun_ceiling"] is None or 0 < w["corun_ceiling"] < float("inf")
        assert doc["ceilings_corun"][name] == w["corun_ceiling"]


def test_children_single_threaded():
    """The children run with every thread pool at one thread (they would inflate the
    one-process baseline otherwise)."""
    import json
    import os
    import subprocess

    env = {**os.environ, **machine_ceiling.ONE_THREAD_ENV}
    code = ("import cv2, json, os; import machine_ceiling as m; m._prepare('compute', 16); "
            "print(json.dumps([cv2.getNumThreads(), os.environ['OMP_NUM_THREADS'], "
            "os.environ['OPENBLAS_NUM_THREADS']]))")
    env["PYTHONPATH"] = str(ROOT / "benchmarks")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=True).stdout
    assert json.loads(out) == [1, "1", "1"]


def test_lscpu_and_step_shapes(doc):
    assert set(machine_ceiling.STEP_SHAPE.values()) <= set(machine_ceiling.WORKLOADS)
    cpu = doc["lscpu"]
    if not cpu:
        pytest.skip("lscpu not available on this machine")
    assert int(cpu["CPU(s)"]) == os.cpu_count()
    assert int(cpu["Thread(s) per core"]) >= 1


def test_bench_scale_puts_steps_beside_their_ceiling(doc):
    import bench_scale

    fake = {"speedup": {"align": 1.5, "degrade": 1.6}, "speedup_vs_one_thread": {"align": 1.8}}
    got = bench_scale.against_ceiling(fake, doc)
    warp, fft = doc["ceilings"]["warp"], doc["ceilings"]["fft"]
    assert got["align"]["shape"] == "warp" and got["align"]["ceiling"] == warp
    assert got["align"]["speedup_of_ceiling"] == pytest.approx(1.5 / warp, rel=2e-3)
    assert got["align"]["speedup_vs_one_thread"] == 1.8
    assert got["degrade"]["shape"] == "fft" and got["degrade"]["ceiling"] == fft
    assert got["align"]["ceiling_corun"] == doc["ceilings_corun"]["warp"]


def test_corun_reps_only_when_both_ran_on_their_cores():
    """A repetition counts as run two at once only when it ran on its core all along and
    the other process's repetitions over the same interval did too (synthetic spans)."""
    full = lambda a, b: (a, b, b - a)  # noqa: E731 - CPU = wall: on a core all along
    half = lambda a, b: (a, b, (b - a) / 2)  # noqa: E731 - descheduled half the time
    ph = machine_ceiling.Phase(
        processes=2, reps=[3, 3], seconds=[3.0, 3.0], cpu_s=[2.5, 2.5], load_1min=[0, 0],
        steal_fraction=None,
        spans=[[full(0, 1), full(1, 2), half(2, 3)],
               [full(0.0, 1.5), half(1.5, 2.5), full(2.5, 3.5)]])
    # process 0: rep 0-1 inside other's full 0-1.5: yes; 1-2 overlaps other's half: no;
    # 2-3 is not full itself: no. Process 1: 0-1.5 inside full 0-1 + 1-2: yes; 2.5-3.5
    # ends after the other's last repetition: no.
    assert sorted(ph.corun_reps()) == [1.0, 1.5]
    assert [s[:2] for s in ph.full_reps(1)] == [(0.0, 1.5), (2.5, 3.5)]


def test_corun_ceiling_from_medians():
    """2 × median alone ÷ median two at once, from the full repetitions."""
    def phase(n, spans):
        return machine_ceiling.Phase(processes=n, reps=[len(s) for s in spans],
                                     seconds=[1.0] * n, cpu_s=[1.0] * n, load_1min=[0, 0],
                                     steal_fraction=None, spans=spans)
    alone = phase(1, [[(i * 0.1, i * 0.1 + 0.1, 0.1) for i in range(10)]])
    # two at once, each repetition 0.125 s and both on their cores: 2 × 0.1 / 0.125 = 1.6
    pair = phase(2, [[(i * 0.125, (i + 1) * 0.125, 0.125) for i in range(8)]] * 2)
    c = machine_ceiling.Ceiling("warp", 0, alone, pair, alone)
    assert c.corun_reps == 16
    assert c.corun_ceiling == pytest.approx(1.6, abs=1e-3)
    # too few such repetitions: no figure
    few = phase(2, [[(0.0, 0.125, 0.125)]] * 2)
    assert machine_ceiling.Ceiling("warp", 0, alone, few, alone).corun_ceiling is None
