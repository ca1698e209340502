"""What a recording holds (the library behind ``twin replay``): the live loop over the recording's frames at full
speed, and a summary.

:func:`summarize` opens a twin HDF5 recording or an ILLumiSense log as a ``replay://`` source
(:class:`twin.io.replay.ReplaySource`, no pacing) and runs :class:`twin.live.LiveLoop` over it with the reference
sinks of :mod:`twin.reference_errors`, so ``twin replay F`` and ``twin live replay://F`` count the same frames the
same way and report the same figures (docs/figures.md): frames, time span, lost samples and resets, complete /
partial / unusable frames, frames with missing peaks, peaks outside their window, invalid nodes, the damage of a
damaged file, the shape error against the recorded truth, the distance to the interrogator's own shape and, when
asked (``tube``), the confidence tube's mean 1σ and its coverage of the truth.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

from twin.calibration import Calibration
from twin.fiber import FiberModel
from twin.io.errors import RecordingDamaged
from twin.io.replay import ReplaySource
from twin.live import Counts, LiveLoop, LiveSummary
from twin.reconstruct import Reconstructor
from twin.reference_errors import TruthError, TruthErrors, TubeFigures, VendorDistance, tube_figures

__all__ = ["ReplaySummary", "TruthErrors", "summarize"]

@dataclass(frozen=True, kw_only=True)
class ReplaySummary(Counts):
    """The summary of one recording (JSON-ready through :meth:`as_dict`; None where unknown, never NaN): the
    live loop's counts over the file (:class:`twin.live.Counts`, which a summary is: ``frames``,
    ``lost_samples``, ``frames_complete``, … as ``twin live`` counts them, docs/figures.md) and what follows.

    Attributes
    ----------
    file, kind, source_url, fiber : str
        The file, ``twin-hdf5`` or ``illumisense-log``, where its frames came from, the fibre model's name.
    complete : bool
        Closed cleanly by its writer and not damaged.
    damaged : bool
    damage : tuple of str
        What is damaged, each naming the place.
    frames_recorded : int
        Frames the file says it holds.
    time_span : float or None
        Last minus first finite timestamp, s.
    recorded_rate_hz : float or None
        (frames − 1) / time_span over the whole recording, Hz (docs/figures.md; not ``rate_hz``, the live loop's
        source rate over the last 2 s of timestamps, which ``twin live`` reports).
    processing_frames_per_s : float or None
        Reconstruction throughput of this run: frames / wall time spent in the loop's processing (docs/figures.md;
        not a benchmark: ``twin bench``).
    skipped_lines : int
        Log lines that did not parse.
    truth : TruthErrors or None
    vendor : dict
        When the recording carries the interrogator's own shape (sensor 0): ``vendor_frames_compared``,
        ``vendor_distance_max_mm``, ``vendor_distance_mean_mm`` (:class:`twin.reference_errors.VendorDistance`);
        empty otherwise.
    tube : dict
        When asked: ``tube_frames``, ``mean_sigma_mm`` and, with a truth, ``tube_truth_frames``, ``coverage_95``
        (:class:`twin.reference_errors.TubeFigures`); empty otherwise.
    notes : tuple of str
    """

    file: str
    kind: str
    complete: bool
    damaged: bool
    source_url: str
    fiber: str
    frames_recorded: int
    time_span: float | None
    recorded_rate_hz: float | None
    processing_frames_per_s: float | None
    skipped_lines: int
    damage: tuple[str, ...] = ()
    truth: TruthErrors | None = None
    vendor: dict = field(default_factory=dict)
    tube: dict = field(default_factory=dict)
    notes: tuple[str, ...] = field(default_factory=tuple)

    def as_dict(self) -> dict:
        out = asdict(self)
        out["damage"], out["notes"] = list(self.damage), list(self.notes)
        out.update(out.pop("vendor"))
        out.update(out.pop("tube"))
        if self.truth is None:
            del out["truth"]
        return out


def summarize(path: str | Path, *, fiber: FiberModel | None = None, calibration: Calibration | None = None,
              method: str = "material", register: str = "kabsch", compare_rate: float | None = 10.0,
              channels_as: str = "cores", n_cores: int | None = None, batch: int = 512,
              salvage: bool = False, handle_signals: bool = False, tube: bool = False,
              twist: float = 0.0) -> ReplaySummary:
    """Reconstruct a recording through the live loop and summarise it.

    Parameters
    ----------
    path : str or Path
        A twin HDF5 recording or an ILLumiSense log.
    fiber, calibration : optional
        Default: the ones stored in the recording (else the reference fibre, said in the notes).
    method, register :
        Reconstruction method; registration before comparing with the truth.
    compare_rate : float or None
        Frames compared with the references per second of the recording's time, as ``twin live`` compares
        them (:mod:`twin.reference_errors`); None: every complete frame.
    channels_as, n_cores :
        Log files: channel layout (:mod:`twin.io.record`).
    batch : int
        Most frames reconstructed per call.
    salvage : bool
        A damaged recording is summarised from its readable frames instead of raising.
    handle_signals : bool
        Ctrl-C ends the run with the summary of what was read (the command's choice).
    tube : bool
        Also the confidence tube's figures on the compared frames (:class:`twin.reference_errors.TubeFigures`,
        the twin's default model error; a propagation per compared frame), for the methods it covers.
    twist : float
        The tube's model error's twist term, 1σ of the catheter's unmeasured twist rate, rad/m
        (:func:`twin.reference_errors.tube_figures`; ``--twist``).

    Raises
    ------
    RecordingDamaged
        The file is damaged and ``salvage`` is False (one line: readable frames of how many, the damage).
    ValueError
        Unreadable file, or frames that do not fit the fibre model.
    """
    path = Path(path)
    source = ReplaySource(path, speed=None, chunk=batch, channels_as=channels_as, n_cores=n_cores,
                          salvage=salvage)
    try:
        notes = []
        if fiber is None:
            fiber = source.fiber
        if fiber is None:
            fiber = FiberModel.paper()
            notes.append("no fibre model in the recording: using the reference fibre (FiberModel.paper())")
        if calibration is None:
            calibration = source.calibration
        shape = source.reader.shape
        if len(source.reader) and shape != (fiber.n_gratings, fiber.n_cores):
            raise ValueError(f"{path}: frames have {shape[0]} gratings × {shape[1]} cores but the fibre model has "
                             f"{fiber.n_gratings} × {fiber.n_cores}; give the sensor's model with --fiber")
    except BaseException:
        source.close()
        raise
    rec = Reconstructor(fiber, calibration, method=method)
    truth, vendor = TruthError(register, per_second=compare_rate), VendorDistance(per_second=compare_rate)
    sinks: list = [truth, vendor]
    tubes = tube_figures(rec, per_second=compare_rate, twist=twist) if tube else None
    if tubes is not None:
        sinks.append(tubes)
    loop = LiveLoop(source, rec, sinks, max_batch=batch, realtime=False, quiet=True)
    run = loop.run(handle_signals=handle_signals)
    info = source.info
    if not salvage:  # damage found while reading (a chunk failing its checksum, an unreadable chunk)
        if info["damaged"]:
            raise RecordingDamaged(info["damage_line"])
        if run.reason == "source failed":
            raise RecordingDamaged(str(run.status.source.get("last_error", "unreadable")))
    if tube and tubes is None:
        notes.append(f"no confidence tube for the {method} method (the material method's only)")
    return _summary(path, info, fiber, run, truth, vendor, notes, tubes)


def _summary(path: Path, info: dict, fiber: FiberModel, run: LiveSummary, truth: TruthError,
             vendor: VendorDistance, notes: list[str], tubes: TubeFigures | None) -> ReplaySummary:
    st, c = run.status, run.counters
    if truth.note is not None:
        notes.append(truth.note)
    result = truth.result()
    if result is None and truth.seen_truth:
        notes.append(truth.note or "truth present but no complete frame to compare")
    if info["skipped_lines"]:
        notes.append(f"{info['skipped_lines']} line(s) skipped, first: {info['skipped'][0]}")
    notes.extend(info["notes"])  # what the reader had to assume (an MCAP recording's)
    if st.reconstruct_errors:
        notes.append(f"reconstruction failed on {st.reconstruct_errors} batch(es): their frames are counted "
                     "unusable")
    if run.reason == "interrupted":
        notes.append(f"interrupted: the figures cover the first {st.frames} frames")
    if not info["complete"] and not info["damaged"]:
        notes.append("the recording was not closed cleanly (killed writer, or still being written)")
    span = c.time_span
    n = st.frames
    rfs = run.processing_frames_per_s
    return ReplaySummary(
        file=str(path),
        kind=info["kind"],
        complete=info["complete"],
        damaged=info["damaged"],
        source_url=info["source_url"],
        fiber=fiber.name,
        frames_recorded=max(n, info["frames_recorded"]),
        time_span=None if span is None else round(span, 6),
        recorded_rate_hz=round((n - 1) / span, 3) if span is not None and span > 0 and n >= 2 else None,
        **vars(c.counts()),
        processing_frames_per_s=None if rfs is None else round(rfs, 1),
        skipped_lines=info["skipped_lines"],
        damage=tuple(info["damage"]),
        truth=result,
        vendor=vendor.as_dict(),
        tube={} if tubes is None else tubes.as_dict(),
        notes=tuple(notes),
    )
