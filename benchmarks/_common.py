"""Helpers shared by the benchmark scripts: whole-call timing, machine load, sizes, tables, JSON results.

How every benchmark times (warpblob and its peers alike): the wall clock
(``time.perf_counter``) around one whole public call, model or points in,
result out; warm (one call first, not timed: compilation, caches, first-touch
memory); the best of ``--repeat`` calls. warpblob's own ``stats`` (seconds per
stage) are kept beside it as the breakdown of the fastest call, never in its
place. Timings taken on a busy machine are slow by an unknown factor, so each
run records the load average (``os.getloadavg``) before and after, prints it,
and writes it into its JSON.

The shared machines also change speed from day to day with no load to show
for it (the same code's interactive steps have moved by 2-3x, a C++ peer's by
1.2-1.4x). So each run also times three fixed probes before and after
(:func:`speed_probe`: a pure-Python loop, a memory-bound numpy pass and one
Warp CPU launch, the three costs an interactive step is made of) and writes
them beside the load: an absolute figure from one day is compared with
another day's through them, and a ratio to a peer only within one run.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import time

import numpy as np
import warp as wp

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")

#: how the figures were taken, written into every JSON
TIMING = "wall clock (time.perf_counter) around each whole call; warm (a first call excluded); best of N = repeat"
#: a 1-minute load average above this is noted as a busy machine (runnable processes besides the benchmark)
BUSY_LOAD = 0.5


def wall_time(fn, repeat: int = 3, *, setup=None):
    """Time whole calls of ``fn`` by the wall clock: one warm-up call, then the best of ``repeat``.

    Args:
        fn: the call to time; with ``setup``, ``fn(setup())``.
        repeat: timed calls.
        setup: optional untimed call before each call of ``fn`` (one fresh input
            per call, for calls that change their input: a cut edits its mesh).

    Returns:
        ``(seconds, result)``: the smallest wall time of the timed calls and what
        that fastest call returned (its ``stats`` are the breakdown of the time).
    """
    fn(*(() if setup is None else (setup(),)))
    best, result = float("inf"), None
    for _ in range(max(1, repeat)):
        arg = () if setup is None else (setup(),)
        t0 = time.perf_counter()
        out = fn(*arg)
        seconds = time.perf_counter() - t0
        if seconds < best:
            best, result = seconds, out
    return best, result


def load_average() -> list[float]:
    """Runnable processes averaged over the last 1, 5 and 15 minutes (``os.getloadavg``)."""
    return [round(v, 2) for v in os.getloadavg()]


def speed_probe() -> dict:
    """The machine's speed now: best of 9 of a pure-Python loop (ms, 10^6 integer additions), a memory-bound
    numpy pass (ms, ``y = 2 x + 1`` over 4 * 10^6 float64: 96 MB moved) and one launch of an empty Warp kernel
    on the CPU (us, what every kernel launch costs on top of its work). Fixed work, so across runs a larger
    figure is a slower machine.

    Example:
        >>> sorted(speed_probe())
        ['numpy_pass_ms', 'python_loop_ms', 'warp_launch_us']
    """

    def best(fn, repeat=9):
        fn()
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return min(times)

    def loop():
        total = 0
        for i in range(1_000_000):
            total += i
        return total

    x = np.ones(4_000_000)
    cpu = wp.get_device("cpu")
    a = wp.zeros(1, dtype=float, device=cpu)

    def launches():
        for _ in range(100):
            wp.launch(_noop_kernel, dim=1, inputs=[a], device=cpu)

    return {
        "python_loop_ms": round(1e3 * best(loop), 2),
        "numpy_pass_ms": round(1e3 * best(lambda: 2.0 * x + 1.0), 2),
        "warp_launch_us": round(1e6 * best(launches) / 100, 1),
    }


@wp.kernel(enable_backward=False)
def _noop_kernel(a: wp.array(dtype=float)):
    a[0] = a[0]


def machine() -> dict:
    return {
        "python": platform.python_version(),
        "warp": wp.__version__,
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "devices": [str(d) for d in wp.get_devices()],
    }


def arguments(ap: argparse.ArgumentParser, full: dict, quick: dict, argv=None) -> argparse.Namespace:
    """Parse ``argv`` with ``--quick``, ``--repeat`` and ``--json`` added; an option left unset
    takes its value from ``quick`` (small sizes, a smoke run under a minute) or ``full``."""
    ap.add_argument("--quick", action="store_true", help="small sizes: a smoke run of under a minute")
    repeat = f"timed calls per figure, the best taken (default {full['repeat']}, quick {quick['repeat']})"
    ap.add_argument("--repeat", type=int, help=repeat)
    ap.add_argument("--json", help="results file (default benchmarks/results/bench_<name>.json; quick runs: none)")
    args = ap.parse_args(argv)
    for key, value in (quick if args.quick else full).items():
        if getattr(args, key, None) is None:
            setattr(args, key, value)
    return args


class Run:
    """One benchmark run: prints its title and the load, then writes the JSON with machine and load.

    Args:
        name: the benchmark's name (``results/bench_<name>.json``).
        title: the line printed first.
        args: the parsed options (:func:`arguments`).
    """

    def __init__(self, name: str, title: str, args: argparse.Namespace):
        self.name, self.args = name, args
        self.started = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
        self._t0 = time.perf_counter()
        self.load_before = load_average()
        print(f"{title}{' (quick)' if args.quick else ''}")
        print(f"timing: {TIMING} = {args.repeat}")
        _print_load("before", self.load_before)
        self.speed_before = speed_probe()
        _print_speed("before", self.speed_before)

    def finish(self, payload: dict) -> str | None:
        """Print the load after the run and write ``payload`` with the run's facts; the path written, if any."""
        load_after = load_average()
        _print_load("after", load_after)
        speed_after = speed_probe()
        _print_speed("after", speed_after)
        path = self.args.json or (None if self.args.quick else os.path.join(RESULTS, f"bench_{self.name}.json"))
        if path is None:
            print("quick run: no JSON written (pass --json PATH to write one)")
            return None
        record = {
            "benchmark": self.name,
            "quick": bool(self.args.quick),
            "timing": TIMING,
            "repeat": self.args.repeat,
            "started": self.started,
            "run_seconds": time.perf_counter() - self._t0,
            "load_average_before": self.load_before,
            "load_average_after": load_after,
            "speed_probe": {"before": self.speed_before, "after": speed_after},
            "machine": machine(),
            **payload,
        }
        write_json(path, record)
        print(f"wrote {path}")
        return path


def _print_load(when: str, load: list[float]) -> None:
    note = f"  (busy: over {BUSY_LOAD}, other work competes for the cores)" if load[0] > BUSY_LOAD else ""
    text = " ".join(f"{v:.2f}" for v in load)
    print(f"load average {when} (1, 5, 15 min): {text} on {os.cpu_count()} cores{note}", flush=True)


def _print_speed(when: str, speed: dict) -> None:
    text = ", ".join(f"{k} {v}" for k, v in speed.items())
    print(f"machine speed {when} (fixed work, smaller is faster): {text}", flush=True)


def table(rows: list[dict], columns: list[tuple[str, str, str]]) -> str:
    """Plain-text table: columns are ``(key, header, format)``."""
    cells = [[h for _, h, _ in columns]]
    for r in rows:
        cells.append([("" if r.get(k) is None else format(r[k], f)) for k, _, f in columns])
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(row, widths)) for row in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def write_json(path: str, payload: dict) -> None:
    """Write ``payload`` to ``path`` atomically (a reader never sees half a file)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(payload, f, indent=2)
        f.write("\n")
    os.replace(tmp, path)
