"""How fast reconstruction (and, when installed, simulation, streaming and studies) runs here (`twin bench`).

The measurements run in a child process pinned to one CPU with single-threaded BLAS, so "per core" means one
core. :func:`report` compares each figure with its goal and, optionally, with an earlier run. The command is
:mod:`twin.cli.bench_command`.

Sections are found through the registry (:mod:`twin.registry`, group ``twin.bench``: ``module:function``
returning a dict), so the simulator's benchmarks live in their own packages without the sensing core naming them.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def sections() -> dict[str, str]:
    """Section → ``"module:function"``; each function takes ``quick: bool`` and returns a flat dict of figures."""
    from twin import registry

    return registry.entries("twin.bench")


#: (section, key) → (comparison, goal, unit) for the report
GOALS: dict[tuple[str, str], tuple[str, float, str]] = {
    ("reconstruct", "latency_us_p50"): ("<=", 100.0, "µs"),
    ("reconstruct", "latency_us_p99"): ("<=", 250.0, "µs"),
    ("reconstruct", "batch_frames_per_s"): (">=", 100_000.0, "frames/s"),
    ("reconstruct", "speedup_vs_baseline"): (">=", 100.0, "×"),
    ("reconstruct", "uncertainty_cost_ratio"): ("<=", 2.0, "×"),
    ("reconstruct", "uncertainty_latency_ratio"): ("<=", 2.0, "×"),
    ("sim", "realtime_factor"): (">=", 2.0, "×"),
    ("sim", "optics_overhead"): ("<=", 0.05, ""),
    ("stream", "max_frames_per_s"): (">=", 40_000.0, "frames/s"),
    ("stream", "decode_frames_per_s"): (">=", 60_000.0, "frames/s"),
}

PAPER_CPP_US = 14_300.0  # the paper's C++ reconstruction per frame (2.6 GHz CPU)


def measure_in_child(sections: list[str], quick: bool = False, cpu: int | None = None) -> dict:
    """Run the sections in a fresh interpreter pinned to one CPU; progress goes to stderr."""
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else [0]
    cpu = cpus[-1] if cpu is None else cpu
    env = dict(os.environ)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        env[var] = "1"

    def pin():  # pragma: no cover - runs in the child
        if hasattr(os, "sched_setaffinity"):
            os.sched_setaffinity(0, {cpu})

    spec = json.dumps({"sections": sections, "quick": quick})
    proc = subprocess.run([sys.executable, "-m", "twin.bench", "--child", spec], env=env, preexec_fn=pin,
                          stdout=subprocess.PIPE, check=False, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"benchmark process failed (exit {proc.returncode})")
    result = json.loads(proc.stdout)
    result["machine"]["pinned_cpu"] = cpu
    return result


def machine() -> dict:
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import numba
    import scipy

    return {
        "cpu": model,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "numba": numba.__version__,
        "platform": platform.platform(),
    }


def _child(spec: dict) -> dict:
    from twin import registry

    result: dict = {"machine": machine()}
    for name in spec["sections"]:
        try:
            fn = registry.load("twin.bench", name)
        except ImportError as exc:
            print(f"bench: skipping {name} ({exc})", file=sys.stderr)
            continue
        print(f"bench: {name} …", file=sys.stderr, flush=True)
        result[name] = fn(quick=spec["quick"])
    return result


# ---------------------------------------------------------------------- the reconstruction section
def _inputs(n_frames: int, seed: int = 0) -> tuple:
    """Wavelengths on the paper's fibre, (n_frames, 18, 4): 64 smooth 3D curvature profiles (three sinusoids
    per component, |k| up to ≈ 60 1/m) with 1 pm noise."""
    from twin import FiberModel, strain

    fiber = FiberModel.paper()
    rng = np.random.default_rng(seed)
    x = fiber.grating_s / fiber.sensed_length
    amp = rng.uniform(-20, 20, (64, 1, 2, 3))  # (profile, grating, component, sinusoid)
    freq = rng.uniform(0.2, 1.5, (64, 1, 2, 3))  # cycles over the sensed length
    phase = rng.uniform(0, 2 * np.pi, (64, 1, 2, 3))
    k = np.sum(amp * np.sin(2 * np.pi * freq * x[:, None, None] + phase), axis=-1)  # (64, 18, 2)
    w = strain.forward(fiber, k[np.arange(n_frames) % 64])
    return fiber, w + rng.normal(scale=1e-3, size=w.shape)


def _latencies(fn, frames: np.ndarray, n: int) -> np.ndarray:
    for i in range(min(50, n)):
        fn(frames[i % len(frames)])
    out = np.empty(n)
    clock = time.perf_counter_ns
    for i in range(n):
        w = frames[i % len(frames)]
        t0 = clock()
        fn(w)
        out[i] = clock() - t0
    return out / 1e3


def naive_baseline(fiber, wavelengths: np.ndarray, step: float = 1e-3) -> np.ndarray:
    """What a user would write first: eqs. 5–7, κ and τ splines, and scipy's solve_ivp on the Frenet–Serret
    equations (RK45, rtol 1e-6, atol 1e-9) with output every ``step``. Positions (n, 3), m."""
    from scipy.integrate import solve_ivp
    from scipy.interpolate import CubicSpline

    from twin import strain

    s = fiber.grating_s
    k = strain.curvature(fiber, wavelengths, method="paper")
    kappa = np.hypot(k[:, 0], k[:, 1])
    theta = np.unwrap(np.arctan2(k[:, 1], k[:, 0]))
    kap, tau = CubicSpline(s, kappa), CubicSpline(s, np.gradient(theta, s))

    def rhs(t, y):
        tt, nn, bb = y[3:6], y[6:9], y[9:12]
        kk, ta = kap(t), tau(t)
        return np.concatenate([tt, kk * nn, -kk * tt + ta * bb, -ta * nn])

    c, sn = np.cos(theta[0]), np.sin(theta[0])
    y0 = np.concatenate([[0, 0, 0], [0, 0, 1], [c, sn, 0], [-sn, c, 0]])
    out = np.arange(0.0, fiber.sensed_length + step / 2, step)
    sol = solve_ivp(rhs, (0.0, fiber.sensed_length), y0, t_eval=out, rtol=1e-6, atol=1e-9)
    return sol.y[:3].T


def bench_reconstruct(quick: bool = False) -> dict:
    """Latency (single frames) and throughput (batches) of the default and paper modes, and the naive baseline;
    ``positions_*``: the default mode asked for positions only (``frames=False``)."""
    from twin import Reconstructor

    fiber, frames = _inputs(1200)
    default = Reconstructor(fiber)
    paper = Reconstructor.paper(fiber)
    n_lat = 800 if quick else 5000
    lat = _latencies(default, frames, n_lat)
    lat_paper = _latencies(paper, frames, n_lat // 2)
    n_batch = 5000 if quick else 20000
    _, batch = _inputs(n_batch, seed=1)
    default(batch[:100])
    times, times_pos = [], []
    for _ in range(2 if quick else 4):
        t0 = time.perf_counter()
        default(batch)
        t1 = time.perf_counter()
        default(batch, frames=False)  # positions only (the material frames not asked)
        times.append(t1 - t0)
        times_pos.append(time.perf_counter() - t1)
    lat_pos = _latencies(lambda w: default(w, frames=False), frames, n_lat // 2)
    lat_base = _latencies(lambda w: naive_baseline(fiber, w), frames, 6 if quick else 40)
    p50 = float(np.percentile(lat, 50))
    unc_ratio, unc_latency_ratio = _uncertainty_cost(fiber, frames, batch[: n_batch // 4], quick)
    return {
        "latency_us_p50": round(p50, 2),
        "latency_us_p99": round(float(np.percentile(lat, 99)), 2),
        "batch_frames_per_s": round(n_batch / min(times)),
        "positions_latency_us_p50": round(float(np.percentile(lat_pos, 50)), 2),
        "positions_batch_frames_per_s": round(n_batch / min(times_pos)),
        "paper_latency_us_p50": round(float(np.percentile(lat_paper, 50)), 2),
        "baseline_latency_us_p50": round(float(np.percentile(lat_base, 50)), 1),
        "speedup_vs_baseline": round(float(np.percentile(lat_base, 50)) / p50, 1),
        "speedup_vs_paper_cpp": round(PAPER_CPP_US / p50, 1),
        "uncertainty_cost_ratio": round(unc_ratio, 2),
        "uncertainty_latency_ratio": round(unc_latency_ratio, 2),
        "frames_latency": n_lat,
        "frames_batch": n_batch,
        "points_per_shape": int(default.s.size),
        "step_m": default.h,
    }


def _uncertainty_cost(fiber, frames: np.ndarray, batch: np.ndarray, quick: bool) -> tuple[float, float]:
    """The uncertainty's own cost (:meth:`twin.uncertainty.Uncertainty.propagate` on shapes already
    reconstructed: noise, both calibration parameters, a model error with the interpolation term and a base
    angle) over the reconstruction's,
    for a batch and for single frames (p50 over p50), measured interleaved so the machine's load hits both."""
    from twin import Calibration, Reconstructor
    from twin.calibration import nominal_delta_theta, nominal_gain
    from twin.uncertainty import TWIN_INTERPOLATION, ModelError, Uncertainty

    cal = Calibration(delta_theta=nominal_delta_theta(fiber), gain=nominal_gain(fiber), delta_theta_std=1e-3,
                      gain_std=1e-2 * nominal_gain(fiber))
    rec = Reconstructor(fiber, cal)
    unc = Uncertainty(rec, model_error=ModelError(0.05, base_angle=1e-3, interpolation=TWIN_INTERPOLATION))
    shapes = rec(batch)
    unc.propagate(shapes[:10], batch[:10])
    t_rec, t_unc = [], []
    for _ in range(2 if quick else 4):
        t0 = time.perf_counter()
        rec(batch)
        t1 = time.perf_counter()
        unc.propagate(shapes, batch)
        t2 = time.perf_counter()
        t_rec.append(t1 - t0)
        t_unc.append(t2 - t1)
    n = 300 if quick else 2000
    single = [rec(frames[i % len(frames)]) for i in range(64)]
    lat_rec, lat_unc = np.empty(n), np.empty(n)
    clock = time.perf_counter_ns
    for i in range(n):
        w = frames[i % 64]
        t0 = clock()
        rec(w)
        t1 = clock()
        unc.propagate(single[i % 64], w)
        lat_rec[i], lat_unc[i] = t1 - t0, clock() - t1
    return min(t_unc) / min(t_rec), float(np.percentile(lat_unc, 50) / np.percentile(lat_rec, 50))


# ---------------------------------------------------------------------- the report
def report(result: dict, previous: dict | None = None) -> str:
    m = result["machine"]
    lines = [f"machine: {m['cpu']} ({m['cores']} cores; measured on CPU {m.get('pinned_cpu')}), Python "
             f"{m['python']}, numpy {m['numpy']}, numba {m['numba']}"]
    for section, figures in result.items():
        if section == "machine":
            continue
        lines.append(f"\n[{section}]")
        for key, value in figures.items():
            goal = GOALS.get((section, key))
            mark = ""
            if goal:
                op, target, unit = goal
                ok = value <= target if op == "<=" else value >= target
                mark = f"   goal {op} {target:g} {unit}: {'met' if ok else 'NOT MET'}"
            before = (previous or {}).get(section, {}).get(key)
            if isinstance(before, int | float) and isinstance(value, int | float) and before:
                mark += f"   (was {before:g}, ×{value / before:.2f})"
            lines.append(f"  {key:26s} {value!s:>12}{mark}")
    return "\n".join(lines)


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        print(json.dumps(_child(json.loads(sys.argv[2]))))
    else:
        sys.exit("usage: twin bench (this module is run by it)")
