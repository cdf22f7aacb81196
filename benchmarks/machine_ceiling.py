"""What this machine gives two processes: the speed-up ceiling of 2 workers over 1.

Plain reference workloads (no geosim code), each run as one process alone and as two
processes at the same time, every process single-threaded (OpenCV, OpenMP, OpenBLAS,
scipy.fft: one thread). A workload runs for a fixed wall time from a common start
instant, counting whole repetitions; its throughput is repetitions per second, and the
**ceiling** is the summed throughput of the two processes ÷ that of the one alone
(2.0 = two cores that do not slow each other down). The alone phase runs before and after
the pair; the ceiling uses their mean, and their spread says how steady the machine was.

Workloads (the shapes of the pipeline's steps):

``compute``
    cv2.GaussianBlur (σ 2) and a 256² complex FFT round trip on a 256² float32 tile: the
    working set fits in one core's L2 cache; measures the cores alone.
``warp``
    cv2.warpAffine, bicubic, of a 5000² uint8 RGB image (a small rotation): the tiles'
    and align's warped reads (75 MB in, 75 MB out).
``fft``
    scipy.fft rfft2, multiply by a transfer function, irfft2 on 2048² float32: an
    optics kernel on a large array (degrade's and align's registration FFTs).
``stream``
    ``b = a * 1.0001 + 0.5`` on a 5000² float32 array: pure memory bandwidth.

A busy machine (other users' jobs) leaves the processes less than their cores, and the
wall-time ceiling then says nothing about the hardware; two more estimates are made:
``ceiling_two_cores`` (2 × work per CPU second two at once ÷ alone) and
``corun_ceiling``, from only the repetitions during which the process(es) ran on their
cores all along (CPU ≥ 0.95 × wall; two at once: both processes): 2 × median repetition
time alone ÷ median two at once (None when fewer than 5 such repetitions occurred).

Per workload and phase it records the repetitions, the seconds, the CPU seconds of each
process (CPU ÷ wall < 1: the process did not get its core), the 1-minute load average and
the hypervisor's steal time over the phase (``/proc/stat``).

Used by bench_scale.py (on by default); alone::

    python benchmarks/machine_ceiling.py [--seconds 2.5] [--workloads compute,warp,fft,stream]
        [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

WORKLOADS = ("compute", "warp", "fft", "stream")
#: A repetition "ran on a core all along" when its CPU time is at least this × its wall time.
FULL = 0.95
#: Fewest such repetitions (alone, and two at once) for a co-run ceiling.
MIN_REPS = 5
#: Which reference workload each pipeline step is shaped like (its ceiling applies).
STEP_SHAPE = {"grid": "warp", "footprints": "warp", "align": "warp", "tiles": "warp",
              "degrade": "fft"}
#: Every thread pool a child could start: one thread each, set before any import.
ONE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
                  "MKL_NUM_THREADS": "1", "OPENCV_FOR_THREADS_NUM": "1",
                  "GDAL_NUM_THREADS": "1"}


@dataclass
class Phase:
    """One phase of one workload: 1 process alone or 2 at once."""

    processes: int
    reps: list[int]
    seconds: list[float]
    cpu_s: list[float]
    load_1min: list[float]
    steal_fraction: float | None
    #: per process, per repetition: (start, end, CPU s); left out of the JSON record
    spans: list[list[tuple[float, float, float]]] = field(default_factory=list, repr=False)

    def full_reps(self, i: int) -> list[tuple[float, float, float]]:
        """Process ``i``'s repetitions that ran on a core all along (CPU ≥ 0.95 × wall)."""
        return [s for s in self.spans[i] if s[1] > s[0] and s[2] >= FULL * (s[1] - s[0])]

    def corun_reps(self) -> list[float]:
        """Wall seconds of the pair's repetitions during which both processes ran on
        their cores: a full repetition of one process whose interval lies inside a run of
        full repetitions of the other."""
        out = []
        for i in range(len(self.spans)):
            for o in (j for j in range(len(self.spans)) if j != i):
                other = self.spans[o]
                for a, b, _ in self.full_reps(i):
                    cover = [s for s in other if s[1] > a and s[0] < b]
                    if (cover and cover[0][0] <= a and cover[-1][1] >= b
                            and all(s[2] >= FULL * (s[1] - s[0]) for s in cover)):
                        out.append(b - a)
        return out

    @property
    def throughput(self) -> float:
        """Summed repetitions per second of the phase's processes."""
        return sum(r / s for r, s in zip(self.reps, self.seconds, strict=True) if s > 0)

    @property
    def per_cpu_s(self) -> float:
        """Repetitions per CPU second, over the phase's processes (what a process does
        with the CPU it gets, whatever share of a core the machine's load left it)."""
        cpu = sum(self.cpu_s)
        return sum(self.reps) / cpu if cpu > 0 else float("nan")

    @property
    def cores_used(self) -> float:
        """CPU seconds ÷ wall seconds, summed over the processes."""
        return sum(c / s for c, s in zip(self.cpu_s, self.seconds, strict=True) if s > 0)


@dataclass
class Ceiling:
    """One workload's ceiling: throughput of 2 processes ÷ 1 process."""

    workload: str
    size: int
    alone_before: Phase
    pair: Phase
    alone_after: Phase
    speedup: float = field(init=False)
    cpu_efficiency: float = field(init=False)
    ceiling_two_cores: float = field(init=False)
    alone_spread: float = field(init=False)
    quiet: bool = field(init=False)
    corun_ceiling: float | None = field(init=False)
    corun_reps: int = field(init=False)

    def __post_init__(self) -> None:
        one = (self.alone_before.throughput + self.alone_after.throughput) / 2
        self.speedup = round(self.pair.throughput / one, 3) if one > 0 else float("nan")
        # work per CPU second two at once ÷ alone: < 1 when the two processes slow each
        # other (shared caches, memory bandwidth, a shared physical core); unlike the wall
        # time it does not depend on how much CPU the machine's other work left them
        eff = (self.alone_before.per_cpu_s + self.alone_after.per_cpu_s) / 2
        self.cpu_efficiency = round(self.pair.per_cpu_s / eff, 3) if eff > 0 else float("nan")
        # what 2 processes would give with two whole cores: 2 × that efficiency
        self.ceiling_two_cores = round(2 * self.cpu_efficiency, 3)
        # the wall-time ceiling means something only when the processes had their cores:
        # the one alone ≥ 0.9 of a core, the pair ≥ 1.8 cores together
        self.quiet = (min(self.alone_before.cores_used, self.alone_after.cores_used) >= 0.9
                      and self.pair.cores_used >= 1.8)
        # the same from the repetitions only during which the processes had their cores
        # (two at once: both of them): 2 × median alone ÷ median two at once. This is what
        # two whole cores give, measurable on a busy machine as long as such moments occur
        import statistics

        alone = [b - a for ph in (self.alone_before, self.alone_after)
                 for a, b, _ in ph.full_reps(0)]
        both = self.pair.corun_reps()
        self.corun_reps = len(both)
        self.corun_ceiling = (round(2 * statistics.median(alone) / statistics.median(both), 3)
                              if len(alone) >= MIN_REPS and len(both) >= MIN_REPS else None)
        lo, hi = sorted((self.alone_before.throughput, self.alone_after.throughput))
        self.alone_spread = round(hi / lo - 1, 3) if lo > 0 else float("nan")


# --------------------------------------------------------------------------- the workloads


def _prepare(workload: str, size: int):
    """The workload's data and one repetition as a closure (data made before the clock)."""
    import cv2
    import numpy as np

    cv2.setNumThreads(1)
    rng = np.random.default_rng(0)
    if workload == "compute":
        import scipy.fft

        n = size or 256
        tile = rng.random((n, n), dtype=np.float32)

        def rep() -> None:
            for _ in range(8):
                cv2.GaussianBlur(tile, (0, 0), 2.0)
                scipy.fft.ifft2(scipy.fft.fft2(tile, workers=1), workers=1)
        return rep
    if workload == "warp":
        n = size or 5000
        img = rng.integers(0, 256, (n, n, 3), dtype=np.uint8)
        m = cv2.getRotationMatrix2D((n / 2, n / 2), 0.05, 1.0)
        m[:, 2] += (0.37, -0.21)
        out = np.empty_like(img)
        # one repetition = one strip of output rows, in turn: the same traffic as the
        # whole warp, in short repetitions (see Ceiling.corun_ceiling)
        strip = max(1, n // 10)
        state = {"r0": 0}

        def rep() -> None:
            r0 = state["r0"]
            r1 = min(n, r0 + strip)
            ms = m.copy()
            ms[:, 2] += m[:, 1] * r0  # output row r0 + y of the whole warp
            cv2.warpAffine(img, ms, (n, r1 - r0), dst=out[r0:r1], flags=cv2.INTER_CUBIC)
            state["r0"] = 0 if r1 >= n else r1
        return rep
    if workload == "fft":
        import scipy.fft

        n = size or 2048
        img = rng.random((n, n), dtype=np.float32)
        fy = np.fft.fftfreq(n).astype(np.float32)[:, None]
        fx = np.fft.rfftfreq(n).astype(np.float32)[None, :]
        otf = np.exp(-20 * (fx * fx + fy * fy)).astype(np.float32)

        def rep() -> None:
            spec = scipy.fft.rfft2(img, workers=1)
            spec *= otf
            scipy.fft.irfft2(spec, s=img.shape, workers=1, overwrite_x=True)
        return rep
    if workload == "stream":
        n = size or 5000
        a = rng.random((n, n), dtype=np.float32)
        b = np.empty_like(a)

        def rep() -> None:
            np.multiply(a, np.float32(1.0001), out=b)
            np.add(b, np.float32(0.5), out=b)
        return rep
    raise ValueError(f"unknown workload {workload!r}; choose among {', '.join(WORKLOADS)}")


def child(workload: str, size: int, seconds: float) -> dict:
    """Prepare ``workload``, say "ready" on stdout, read the start instant
    (``time.time()``) from stdin, then run it from that instant for ``seconds``: whole
    repetitions, their wall and CPU seconds."""
    rep = _prepare(workload, size)
    rep()  # warm-up: allocations, page faults, OpenCV's tables
    print("ready", flush=True)
    start_at = float(sys.stdin.readline())
    late = time.time() - start_at
    while time.time() < start_at:
        time.sleep(min(0.01, max(0.0, start_at - time.time())))
    t0, c0 = time.perf_counter(), time.process_time()
    end = t0 + seconds
    reps = 0
    spans = []  # per repetition: start and end (time.time(), shared by the processes), CPU s
    while True:
        w0, p0 = time.time(), time.process_time()
        rep()
        spans.append((w0, time.time(), time.process_time() - p0))
        reps += 1
        if time.perf_counter() >= end:
            break
    return {"reps": reps, "seconds": time.perf_counter() - t0,
            "cpu_s": time.process_time() - c0, "late_s": max(0.0, late), "spans": spans}


# --------------------------------------------------------------------------- measuring


def _steal() -> tuple[int, int] | None:
    """(steal, total) jiffies of all CPUs from /proc/stat; None where absent."""
    try:
        first = Path("/proc/stat").read_text().splitlines()[0].split()
    except OSError:
        return None
    vals = [int(v) for v in first[1:]]
    return (vals[7] if len(vals) > 7 else 0), sum(vals[:8])


def _phase(workload: str, size: int, processes: int, seconds: float,
           lead_s: float) -> Phase:
    """``processes`` children of ``workload`` started together; their records."""
    env = {**os.environ, **ONE_THREAD_ENV}
    procs = [subprocess.Popen([sys.executable, __file__, "--child", workload, "--size",
                               str(size), "--seconds", str(seconds)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                              env=env)
             for _ in range(processes)]
    for p in procs:  # every child prepared and warmed up before the common start
        if p.stdout.readline().strip() != "ready":
            p.wait()
            raise RuntimeError(f"ceiling probe {workload} failed (exit {p.returncode})")
    load0 = os.getloadavg()[0]
    start_at = time.time() + lead_s
    for p in procs:
        p.stdin.write(f"{start_at!r}\n")
        p.stdin.flush()
    s0 = _steal()
    recs = []
    for p in procs:
        out, _ = p.communicate()
        if p.returncode:
            raise RuntimeError(f"ceiling probe {workload} failed (exit {p.returncode})")
        recs.append(json.loads(out.strip().splitlines()[-1]))
    s1 = _steal()
    steal = (round((s1[0] - s0[0]) / (s1[1] - s0[1]), 4)
             if s0 and s1 and s1[1] > s0[1] else None)
    if any(r["late_s"] > 0 for r in recs):
        # a child that started late ran partly alone: say so rather than report a ceiling
        raise RuntimeError(f"ceiling probe {workload}: a process was not ready at the start "
                           f"instant ({max(r['late_s'] for r in recs):.2f} s late)")
    return Phase(processes=processes, reps=[r["reps"] for r in recs],
                 spans=[[tuple(x) for x in r["spans"]] for r in recs],
                 seconds=[round(r["seconds"], 4) for r in recs],
                 cpu_s=[round(r["cpu_s"], 4) for r in recs],
                 load_1min=[round(load0, 2), round(os.getloadavg()[0], 2)],
                 steal_fraction=steal)


def measure(workloads: tuple[str, ...] = WORKLOADS, seconds: float = 2.5,
            sizes: dict[str, int] | None = None, lead_s: float = 0.2) -> list[Ceiling]:
    """The ceiling of each workload: alone, two at once, alone again."""
    sizes = sizes or {}
    out = []
    for w in workloads:
        size = sizes.get(w, 0)
        phases = [_phase(w, size, n, seconds, lead_s) for n in (1, 2, 1)]
        out.append(Ceiling(w, size, *phases))
    return out


def lscpu() -> dict:
    """lscpu's fields (threads per core, cores, caches, model, hypervisor); {} without it."""
    try:
        proc = subprocess.run(["lscpu", "-J"], capture_output=True, text=True, timeout=10)
        rows = json.loads(proc.stdout)["lscpu"]
    except (OSError, ValueError, KeyError, subprocess.SubprocessError):
        return {}
    keep = ("Model name", "Thread(s) per core", "Core(s) per socket", "Socket(s)", "CPU(s)",
            "L1d cache", "L2 cache", "L3 cache", "Hypervisor vendor", "NUMA node(s)")
    flat: dict[str, str] = {}

    def walk(items: list[dict]) -> None:
        for it in items:
            flat[it["field"].rstrip(":")] = it.get("data")
            walk(it.get("children", []))
    walk(rows)
    return {k: flat[k] for k in keep if k in flat}


def _record(c: Ceiling) -> dict:
    """``c`` as JSON-ready fields, without the repetitions' spans."""
    doc = asdict(c)
    for key in ("alone_before", "pair", "alone_after"):
        doc[key].pop("spans", None)
    return doc


def probe(workloads: tuple[str, ...] = WORKLOADS, seconds: float = 2.5,
          sizes: dict[str, int] | None = None) -> dict:
    """The whole probe as a JSON-ready record: lscpu, then per workload the phases and
    the ceiling."""
    t0 = time.perf_counter()
    ceilings = measure(workloads, seconds, sizes)
    return {"lscpu": lscpu(), "seconds_per_phase": seconds,
            "ceilings": {c.workload: c.speedup for c in ceilings},
            "ceilings_two_cores": {c.workload: c.ceiling_two_cores for c in ceilings},
            "quiet": {c.workload: c.quiet for c in ceilings},
            "ceilings_corun": {c.workload: c.corun_ceiling for c in ceilings},
            "workloads": {c.workload: _record(c) for c in ceilings},
            "step_shape": STEP_SHAPE,
            "cores_used": {c.workload: {"alone": [round(c.alone_before.cores_used, 2),
                                                  round(c.alone_after.cores_used, 2)],
                                        "pair": round(c.pair.cores_used, 2)}
                           for c in ceilings}, "probe_s": round(time.perf_counter() - t0, 1)}


def describe(doc: dict) -> str:
    """One line per workload."""
    lines = []
    for name, w in doc["workloads"].items():
        a, p, b = w["alone_before"], w["pair"], w["alone_after"]
        cores = doc["cores_used"][name]
        quiet = ("" if w["quiet"] else
                 f" (NOT quiet: cores used alone {cores['alone'][0]}/{cores['alone'][1]},"
                 f" pair {cores['pair']})")
        steal = p["steal_fraction"] if p["steal_fraction"] is not None else "–"
        corun = ("–" if w["corun_ceiling"] is None else f"{w['corun_ceiling']:.2f}×")
        lines.append(f"{name}: 2 processes {w['speedup']:.2f}× one in wall time{quiet}, "
                     f"{corun} from the {w['corun_reps']} repetitions run with both on "
                     "their cores, "
                     f"{w['ceiling_two_cores']:.2f}× given two whole cores (work per CPU-s "
                     f"{w['cpu_efficiency']:.2f}× alone; alone spread {w['alone_spread']:.0%};"
                     f" load {a['load_1min'][0]:.1f}→{b['load_1min'][1]:.1f}; steal {steal})")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workloads", default=",".join(WORKLOADS))
    ap.add_argument("--seconds", type=float, default=2.5, help="wall seconds per phase")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--child")
    ap.add_argument("--size", type=int, default=0)
    a = ap.parse_args()
    if a.child:
        print(json.dumps(child(a.child, a.size, a.seconds)))
        return
    doc = probe(tuple(w.strip() for w in a.workloads.split(",")), a.seconds)
    doc["load_average_at_end"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(doc["ceilings"]))
    print(describe(doc))
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(doc, indent=2) + "\n")


if __name__ == "__main__":
    main()
