"""spun-twist: a spun multi-core fibre in the twin — twist measured against twist ignored (docs/spun-fibers.md).

Friction twists the catheter in grooves and sheaths, and straight cores cannot see it. Here the same motions are
read by a spun fibre (``FiberModel.spun``: centre + 3 outer cores at 120°, r = 35 µm, ``--spin`` turns/m) and by
today's straight-core fibre (``FiberModel.paper()``), from one physics run:

1. **groove** — library planar shapes (``--shapes``) settled in the covered groove (sim://static, fixture groove),
   read ``--repeats`` times with fresh interrogator noise;
2. **rotation** — the catheter turned through one revolution in ``--steps`` steps inside the pre-bent sheath
   (sim://sheath-rotate, the paper's rotation experiment), read at ``--rate`` Hz while turning and dwelling.

The spun fibre's wavelengths come from the twin (the exact helical path length of the rod's curvature and twist,
with the realistic optics: noise ``--noise``, drift ``--drift``, quantisation, λ0 spread, intrinsic twist, the
as-built core spacing error, per-core S_T); the straight fibre's from the same rod's curvature through its own
optics with the same effects. Every frame is reconstructed three ways (each with its twin's true calibration): spun
with the twist measured, spun with the twist ignored, straight cores. Errors are distances to the rod's centreline
per frame, with the reconstruction placed by the rod's true base pose (position and material frame at s = 0, a
tracked base, no registration: a roll anywhere along the fibre shows); ``registered_max_error_mm`` registers rigidly
first (Kabsch on arc length, as static-shapes reports), which hides a roll made before the bends.

Reported (``--json``; ``summary``):

* ``max_error_mm_twist_measured`` / ``max_error_mm_twist_ignored`` / ``straight_cores_max_error_mm`` — the largest
  per-frame max error over both parts;
* ``tip_twist_rms_error_deg`` — RMS over all frames of the measured tip twist ψ(L) = ∫τ ds against the rod's
  (its Darboux vector's tangential component integrated over the sensed length);
* per part the same, the true tip twist's range, and for the groove the errors of the frames' mean wavelengths
  (a held reading: the noise falls by √repeats);
* ``resolution`` — the twist resolution against wavelength noise and spin rate: per-grating 1σ of τ (linear error
  propagation, docs/spun-fibers.md §3) and the tip twist's 1σ per frame (400 noisy frames of a straight fibre);
  and the twist read from a 10 K temperature change with the per-core S_T mismatch;
* ``payoff`` — the recorded rod states read again through spun fibres of every spin rate and noise level of the
  resolution table (optics and reconstruction only, no physics): the largest error with the twist measured, and
  its error when the frames of each static shape and each rotation dwell are averaged.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from dataclasses import asdict, dataclass

import numpy as np

from sim_interrogator.optics import Optics, OpticsConfig
from sim_interrogator.setups import StaticShape
from sim_interrogator.sheath_setups import SheathRotate
from sim_interrogator.sim import SimInterrogator
from twin import FiberModel, Reconstructor, jsonout, metrics, shapes
from twin.calibration import nominal_delta_theta

AS_BUILT_SPACING = 1.039 / (math.pi / 3)  # the paper's identified Δθ relative to nominal, applied to any layout


@dataclass(frozen=True)
class Params:
    """Parameters of the experiment (SI units; wavelength noise in nm)."""

    shapes: tuple[str, ...] = ("arc", "hook", "clothoid")
    repeats: int = 5
    steps: int = 4
    rate: float = 20.0
    spin: float = 50.0
    noise: float = 1e-3
    spin_rates: tuple[float, ...] = (20.0, 50.0, 100.0, 170.0)
    noises: tuple[float, ...] = (1e-4, 1e-3, 3e-3)
    optics: str = "realistic"
    friction: float = 0.2
    segments: int = 100
    seed: int = 0
    rotation: bool = True
    drift: float = 2e-4


@dataclass
class _Part:
    """Per-frame records of one part (lists while running, arrays after)."""

    name: str
    curvature: list  # true (k_x, k_y) at the gratings (n_g, 2)
    twist: list  # true τ at the gratings (n_g,)
    positions: list  # true centreline samples (m, 3)
    tip_twist: list  # true ψ(L), rad
    spun: list  # spun fibre wavelengths (n_g, 4)
    straight: list  # straight fibre wavelengths (n_g, 4)
    group: list  # frames that form one held measurement (a static shape, a rotation dwell) share a group id
    base_frames: list  # the rod's true material frame at s = 0 (3, 3): the tracked base pose
    base_positions: list  # and its position (3,)
    truth_s: np.ndarray | None = None

    @classmethod
    def new(cls, name: str) -> _Part:
        return cls(name, [], [], [], [], [], [], [], [], [])

    def add(self, frame, tip_twist: float, straight: np.ndarray, group: int) -> None:
        t = frame.truth
        self.truth_s = t.s
        self.curvature.append(t.curvature)
        self.twist.append(t.twist)
        self.positions.append(t.positions)
        self.tip_twist.append(tip_twist)
        self.spun.append(frame.wavelengths)
        self.straight.append(straight)
        self.group.append(group)
        self.base_frames.append(t.frames[0])
        self.base_positions.append(t.positions[0])

    def arrays(self) -> dict:
        return {k: np.asarray(getattr(self, k)) for k in ("curvature", "twist", "positions", "tip_twist", "spun",
                                                            "straight", "group", "base_frames", "base_positions")}


def _config(fiber: FiberModel, params: Params, seed: int) -> OpticsConfig:
    if params.optics == "ideal":
        return OpticsConfig.ideal(seed=seed)
    return OpticsConfig(seed=seed, noise=params.noise, drift=params.drift,
                        delta_theta=nominal_delta_theta(fiber) * AS_BUILT_SPACING)


def _true_tip_twist(sim: SimInterrogator) -> float:
    """∫ τ ds over the sensed length from the rod's Darboux vector on a 0.5 mm grid, rad."""
    s = np.linspace(0.0, sim.fiber.sensed_length, 341)
    return float(np.trapezoid(sim.reader.read(sim.data).twist_at(s), s))


def _run_groove(params: Params, spun: FiberModel, straight: Optics, part: _Part, say) -> SimInterrogator | None:
    sim = None
    for i, name in enumerate(params.shapes):
        t0 = time.perf_counter()
        sim = SimInterrogator(StaticShape(name, "groove", segments=params.segments), spun,
                              _config(spun, params, params.seed + i))
        for _ in range(params.repeats):
            f = sim.read()
            w, _ = straight.wavelengths(f.truth.curvature, t=sim.time)
            part.add(f, _true_tip_twist(sim), w, i)
        say(f"groove {name}: settled and read in {time.perf_counter() - t0:.1f} s wall; true tip twist "
            f"{math.degrees(part.tip_twist[-1]):+.2f}°")
    return sim


def _run_rotation(params: Params, spun: FiberModel, straight: Optics, part: _Part, say) -> SimInterrogator:
    t0 = time.perf_counter()
    setup = SheathRotate(steps=params.steps, friction=params.friction, segments=params.segments)
    sim = SimInterrogator(setup, spun, _config(spun, params, params.seed + 100), rate=params.rate)
    n = int(setup.duration * params.rate + 1e-9) + 1
    say(f"rotation: settled in {time.perf_counter() - t0:.1f} s wall; {n} frames over {setup.duration:.1f} s …")
    for k in range(n):
        f = sim.read()
        w, _ = straight.wavelengths(f.truth.curvature, t=sim.time)
        # the last 0.5 s of each dwell is one held measurement; frames while turning get their own group
        t = k / params.rate
        dwell = np.flatnonzero((t > setup.dwell_ends - 0.5 - 1e-9) & (t <= setup.dwell_ends + 1e-9))
        part.add(f, _true_tip_twist(sim), w, int(dwell[0]) if dwell.size else -1 - k)
    say(f"rotation: done in {time.perf_counter() - t0:.1f} s wall")
    return sim


def _errors(rec: Reconstructor, wavelengths: np.ndarray, part: dict, truth_s: np.ndarray,
            register: str = "base") -> np.ndarray:
    """Per-frame max distance to the rod, m: the reconstruction placed with the rod's true base pose (``base``,
    no registration: what a tracked base gives) or registered rigidly (``kabsch``, the shape alone)."""
    shape = rec(wavelengths)
    if register == "base":
        pos = np.einsum("nij,npj->npi", part["base_frames"], shape.positions) + part["base_positions"][:, None]
        return metrics.shape_error(pos, part["positions"], s=shape.s, truth_s=truth_s, register="none").max
    return metrics.shape_error(shape.positions, part["positions"], s=shape.s, truth_s=truth_s).max


def _held(wavelengths: np.ndarray, part: dict) -> tuple[np.ndarray, np.ndarray]:
    """Mean wavelengths per held measurement (groups ≥ 0) and the index of one frame of each."""
    groups = np.unique(part["group"][part["group"] >= 0])
    idx = np.array([np.flatnonzero(part["group"] == g)[0] for g in groups], dtype=int)
    with warnings.catch_warnings():  # a peak lost in every frame of a group stays NaN (a missing peak)
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.array([np.nanmean(wavelengths[part["group"] == g], axis=0) for g in groups])
    return mean, idx


def _part_result(part: dict, truth_s, recs: dict) -> tuple[dict, dict, np.ndarray]:
    """A part's report, its per-frame max errors per reconstruction (m) and its measured tip twist (rad)."""
    err = {k: _errors(r, part[w], part, truth_s) for k, (r, w) in recs.items()}
    reg = {k: _errors(r, part[w], part, truth_s, "kabsch") for k, (r, w) in recs.items()}
    tip = recs["measured"][0].twist_angle(part["spun"])[:, -1]
    out = {
        "frames": int(part["spun"].shape[0]),
        "lost_peaks": {"spun": int(np.isnan(part["spun"]).sum()), "straight": int(np.isnan(part["straight"]).sum())},
        "max_error_mm": {k: _mm(np.nanmax(v)) for k, v in err.items()},
        "mean_error_mm": {k: _mm(np.nanmean(v)) for k, v in err.items()},
        "registered_max_error_mm": {k: _mm(np.nanmax(v)) for k, v in reg.items()},
        "true_tip_twist_deg": {"min": _deg(part["tip_twist"].min()), "max": _deg(part["tip_twist"].max())},
        "tip_twist_rms_error_deg": _deg(np.sqrt(np.mean((tip - part["tip_twist"]) ** 2))),
    }
    if np.any(part["group"] >= 0):
        sub = {k: v[_held(part["spun"], part)[1]] for k, v in part.items()}
        held = {}
        for k, (r, w) in recs.items():
            mean, _ = _held(part[w], part)
            held[k] = _mm(np.nanmax(_errors(r, mean, sub, truth_s)))
        mean, idx = _held(part["spun"], part)
        tip_h = recs["measured"][0].twist_angle(mean)[:, -1]
        out["held_max_error_mm"] = held
        out["held_tip_twist_rms_error_deg"] = _deg(np.sqrt(np.mean((tip_h - part["tip_twist"][idx]) ** 2)))
    return out, err, tip


def resolution(params: Params) -> dict:
    """Twist resolution against wavelength noise and spin rate (predicted per grating, simulated at the tip),
    and the twist a 10 K temperature change reads through a 0.3 % per-core S_T mismatch."""
    rows = []
    for spin in params.spin_rates:
        fiber = FiberModel.spun(spin)
        for noise in params.noises:
            rec = Reconstructor(fiber, wavelength_noise=noise)
            rng = np.random.default_rng(params.seed)
            w = fiber.lambda0 + noise * rng.standard_normal((400, *fiber.lambda0.shape))
            tip = rec.twist_angle(w)[:, -1]
            rows.append({"spin_turns_per_m": spin, "noise_pm": noise * 1e3,
                         "tau_std_rad_per_m": float(rec.curvature(fiber.lambda0).twist_rate_std.mean()),
                         "tip_twist_std_deg": _deg(tip.std())})
    fiber = FiberModel.spun(params.spin)
    o = Optics(fiber, OpticsConfig.ideal(thermal_mismatch=0.003, fiber_seed=params.seed))
    w, _ = o.wavelengths(np.zeros((fiber.n_gratings, 2)), delta_T=10.0)
    rec = Reconstructor(fiber, o.true_calibration())
    thermal = {"delta_T_K": 10.0, "thermal_mismatch": 0.003,
               "tau_rad_per_m": float(np.abs(rec.curvature(w).twist_rate).max()),
               "tip_twist_deg": _deg(abs(rec.twist_angle(w)[-1]))}
    return {"table": rows, "thermal": thermal}


def payoff(params: Params, parts: dict[str, dict]) -> list[dict]:
    """The recorded rod states read through spun fibres of each spin rate and noise (no physics)."""
    rows = []
    for spin in params.spin_rates:
        fiber = FiberModel.spun(spin)
        for noise in params.noises:
            cfg = _config(fiber, params, params.seed + 7).replace(noise=noise if params.optics != "ideal" else 0.0)
            optics = Optics(fiber, cfg)
            rec = Reconstructor(fiber, optics.true_calibration(), wavelength_noise=max(noise, 1e-5))
            worst = held_worst = 0.0
            lost = 0
            for part, truth_s in parts.values():
                w, _ = optics.wavelengths(part["curvature"], twist_rate=part["twist"])
                lost += int(np.isnan(w).sum())
                worst = max(worst, float(np.nanmax(_errors(rec, w, part, truth_s))))
                if np.any(part["group"] >= 0):
                    mean, idx = _held(w, part)
                    sub = {k: v[idx] for k, v in part.items()}
                    held_worst = max(held_worst, float(np.nanmax(_errors(rec, mean, sub, truth_s))))
            rows.append({"spin_turns_per_m": spin, "noise_pm": noise * 1e3, "max_error_mm": _mm(worst),
                         "held_max_error_mm": _mm(held_worst), "lost_peaks": lost})
    return rows


def run_experiment(params: Params, progress=None) -> dict:
    """Run both parts and the resolution study; returns the JSON-ready result."""
    if params.optics not in ("realistic", "ideal"):
        raise ValueError(f"optics must be realistic or ideal; got {params.optics!r}")
    if params.repeats < 1 or params.steps < 1 or not params.rate > 0:
        raise ValueError("repeats and steps must be at least 1 and rate positive")
    if not params.noise >= 0:
        raise ValueError(f"noise must be >= 0 nm, got {params.noise}")
    if params.spin == 0 or 0 in params.spin_rates:
        raise ValueError("spin rates must be non-zero (0 turns/m is a straight-core fibre: it cannot see twist)")
    for name in params.shapes:
        if not shapes.get(name).planar:
            raise ValueError(f"shape {name!r} is not planar; the groove holds the planar shapes only")
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    spun = FiberModel.spun(params.spin)
    paper = FiberModel.paper()
    straight = Optics(paper, _config(paper, params, params.seed + 50))
    recorded: dict[str, tuple[dict, np.ndarray]] = {}
    runs = []
    if params.shapes:
        part = _Part.new("groove")
        sim = _run_groove(params, spun, straight, part, say)
        recorded["groove"] = (part.arrays(), part.truth_s)
        runs.append(sim)
    if params.rotation:
        part = _Part.new("rotation")
        sim = _run_rotation(params, spun, straight, part, say)
        recorded["rotation"] = (part.arrays(), part.truth_s)
        runs.append(sim)
    if not recorded:
        raise ValueError("nothing to run: give --shapes or leave the rotation on")
    noise = params.noise if params.noise > 0 else 1e-5
    cal = runs[-1].optics.true_calibration()
    recs = {
        "measured": (Reconstructor(spun, cal, wavelength_noise=noise), "spun"),
        "ignored": (Reconstructor(spun, cal, twist=False), "spun"),
        "straight": (Reconstructor(paper, straight.true_calibration()), "straight"),
    }
    parts, all_err, tips, truths = {}, {k: [] for k in recs}, [], []
    for name, (part, truth_s) in recorded.items():
        parts[name], err, tip = _part_result(part, truth_s, recs)
        for k in recs:
            all_err[k].append(err[k])
        tips.append(tip)
        truths.append(part["tip_twist"])
    tip_err = np.concatenate(tips) - np.concatenate(truths)
    say("resolution and payoff tables …")
    res = resolution(params)
    pay = payoff(params, recorded)
    summary = {
        "max_error_mm_twist_measured": _mm(np.nanmax(np.concatenate(all_err["measured"]))),
        "max_error_mm_twist_ignored": _mm(np.nanmax(np.concatenate(all_err["ignored"]))),
        "tip_twist_rms_error_deg": _deg(np.sqrt(np.mean(tip_err**2))),
        "straight_cores_max_error_mm": _mm(np.nanmax(np.concatenate(all_err["straight"]))),
        "true_tip_twist_max_abs_deg": _deg(np.abs(np.concatenate(truths)).max()),
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    return {"scenario": "spun-twist", "params": asdict(params), "summary": summary, "parts": parts,
            "resolution": res, "payoff": pay}


def _mm(x) -> float | None:
    x = float(x)
    return round(x * 1e3, 4) if math.isfinite(x) else None


def _deg(x) -> float | None:
    x = float(x)
    return round(math.degrees(x), 4) if math.isfinite(x) else None


def text_report(result: dict) -> str:
    s, p = result["summary"], result["params"]
    lines = [f"spun-twist: spun fibre {p['spin']:g} turns/m, {p['noise'] * 1e3:g} pm noise, optics {p['optics']}",
             "", f"{'part':<10} {'measured':>10} {'ignored':>10} {'straight':>10}   max error mm (per frame)"]
    for name, part in result["parts"].items():
        e = part["max_error_mm"]
        lo, hi = part["true_tip_twist_deg"]["min"], part["true_tip_twist_deg"]["max"]
        lines.append(f"{name:<10} {e['measured']:>10} {e['ignored']:>10} {e['straight']:>10}   "
                     f"true tip twist {lo:+.2f}…{hi:+.2f}°, tip twist RMS error {part['tip_twist_rms_error_deg']:.2f}°")
        if "held_max_error_mm" in part:
            h = part["held_max_error_mm"]
            lines.append(f"{'  held':<10} {h['measured']:>10} {h['ignored']:>10} {h['straight']:>10}   "
                         f"(mean of held frames) tip twist RMS error {part['held_tip_twist_rms_error_deg']:.2f}°")
    lines += ["", "summary: " + json.dumps(s), "", "twist resolution (per frame):",
              f"{'turns/m':>8} {'noise pm':>9} {'σ_τ rad/m':>10} {'σ_ψ(L) °':>9}"]
    for r in result["resolution"]["table"]:
        lines.append(f"{r['spin_turns_per_m']:>8g} {r['noise_pm']:>9g} {r['tau_std_rad_per_m']:>10.3f} "
                     f"{r['tip_twist_std_deg']:>9.3f}")
    th = result["resolution"]["thermal"]
    lines += [f"10 K with a 0.3 % per-core S_T mismatch reads as {th['tau_rad_per_m']:.3f} rad/m "
              f"({th['tip_twist_deg']:.2f}° at the tip)", "", "payoff (recorded rod states, twist measured):",
              f"{'turns/m':>8} {'noise pm':>9} {'max mm':>8} {'held max mm':>12} {'lost peaks':>11}"]
    for r in result["payoff"]:
        lines.append(f"{r['spin_turns_per_m']:>8g} {r['noise_pm']:>9g} {r['max_error_mm']:>8} "
                     f"{r['held_max_error_mm']:>12} {r['lost_peaks']:>11}")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ command line
def _floats(text: str, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ValueError(f"{what}: expected comma-separated numbers, got {text!r}") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise ValueError(f"{what}: expected finite numbers, got {text!r}")
    return values


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = Params()
    parser.add_argument("--shapes", default=",".join(d.shapes),
                        help=f"planar shapes in the groove, comma-separated, '' for none (default {','.join(d.shapes)})"
                        )
    parser.add_argument("--repeats", type=int, default=d.repeats, help=f"frames per groove shape (default {d.repeats})")
    parser.add_argument("--steps", type=int, default=d.steps, help=f"rotation steps over one turn (default {d.steps})")
    parser.add_argument("--no-rotation", action="store_true", help="skip the rotation in the sheath")
    parser.add_argument("--rate", type=float, default=d.rate, help=f"rotation frame rate, Hz (default {d.rate:g})")
    parser.add_argument("--spin", type=float, default=d.spin, help=f"spin rate, turns/m (default {d.spin:g})")
    parser.add_argument("--noise", type=float, default=d.noise * 1e3,
                        help=f"white wavelength noise, pm (default {d.noise * 1e3:g})")
    parser.add_argument("--drift", type=float, default=d.drift * 1e3,
                        help=f"random-walk wavelength drift per peak, pm/√s (default {d.drift * 1e3:g})")
    parser.add_argument("--spin-rates", default=",".join(f"{v:g}" for v in d.spin_rates),
                        help="spin rates of the resolution and payoff tables, turns/m")
    parser.add_argument("--noises", default=",".join(f"{v * 1e3:g}" for v in d.noises),
                        help="noise levels of the resolution and payoff tables, pm")
    parser.add_argument("--optics", choices=("realistic", "ideal"), default=d.optics)
    parser.add_argument("--friction", type=float, default=d.friction, help="catheter–sheath friction")
    parser.add_argument("--segments", type=int, default=d.segments, help="rod segments")
    parser.add_argument("--seed", type=int, default=d.seed)
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def params_from_args(args: argparse.Namespace) -> Params:
    names = tuple(s.strip() for s in args.shapes.split(",") if s.strip())
    for n in names:
        shapes.get(n)  # a clear error for an unknown shape
    for name in ("noise", "drift"):
        v = getattr(args, name)
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"--{name}: expected pm >= 0, got {v}")
    return Params(names, args.repeats, args.steps, args.rate, args.spin, args.noise * 1e-3,
                  _floats(args.spin_rates, "--spin-rates"),
                  tuple(v * 1e-3 for v in _floats(args.noises, "--noises")), args.optics, args.friction,
                  args.segments, args.seed, not args.no_rotation, args.drift * 1e-3)


def run(args: argparse.Namespace) -> int:
    params = params_from_args(args)
    FiberModel.spun(params.spin)  # a clear error for a nonsense spin rate before any physics
    result = run_experiment(params, progress=lambda msg: print(msg, file=sys.stderr, flush=True))
    print(jsonout.dumps(result, indent=2) if args.json else text_report(result))
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="spun_twist", description=__doc__)
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
