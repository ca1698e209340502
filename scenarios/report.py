"""`--report DIR` for any scenario: PNG plots and a short markdown summary a person reads instead of JSON.

A :class:`Report` collects paragraphs, tables and figures and writes ``DIR/report.md`` with the PNGs beside
it. The figure helpers cover what a reader of the paper expects from every experiment:

* :func:`shape_overlays`: reconstruction, truth and fixture of each shape in one panel (the paper's static
  figure), in the plane that shows the shape best;
* :func:`error_along_arc`: the distance to the truth along the arc length, one line per shape;
* :func:`per_shape_errors`: max and mean error per shape (or per angle, per cycle) with the paper's figures as
  reference lines;
* :func:`error_over_time`, :func:`tip_trajectories`, :func:`curvature_profiles` for the dynamic experiments.

Every figure has a title, units on its axes and, through ``calibration`` (a
:attr:`scenarios._common.calibration.UsedCalibration.label`-like text), the calibration it was made with.
Matplotlib runs headless (Agg).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

__all__ = [
    "Report",
    "curvature_profiles",
    "error_along_arc",
    "error_over_time",
    "overlay_panels",
    "per_shape_errors",
    "pyplot",
    "register_onto",
    "shape_overlays",
    "stamp",
    "tip_trajectories",
]

#: Colours of the pipelines, the same in every figure.
COLOURS = {"default": "C0", "paper": "C1", "paper-literal": "C3"}
LABELS = {"default": "default pipeline", "paper": "paper's pipeline (guarded)", "paper-literal": "paper's, literal"}


def pyplot():
    """matplotlib.pyplot on the headless Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


class Report:
    """A markdown report with figures, written to ``directory``.

    Parameters
    ----------
    directory : str or Path
        Created if missing.
    title : str
    calibration : str, optional
        The calibration the results were made with (a label); stated under the title and stamped on every figure
        that does not carry it yet.
    """

    def __init__(self, directory: str | Path, title: str, calibration: str | None = None):
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.calibration = calibration
        self.lines = [f"# {title}", ""] + ([f"*{calibration}*", ""] if calibration else [])

    def text(self, paragraph: str) -> None:
        self.lines += [paragraph, ""]

    def table(self, headers: Sequence[str], rows: Sequence[Sequence]) -> None:
        def cell(v):
            return f"{v:.3f}" if isinstance(v, float) else str(v)

        self.lines += ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
        self.lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
        self.lines.append("")

    def figure(self, name: str, fig, caption: str = "") -> Path:
        """Save a matplotlib figure as ``name``.png and reference it in the report."""
        path = self.dir / f"{name}.png"
        stamp(fig, self.calibration)
        fig.savefig(path, dpi=110, bbox_inches="tight")
        pyplot().close(fig)
        self.lines += [f"![{caption or name}]({path.name})", ""]
        if caption:
            self.lines += [f"*{caption}*", ""]
        return path

    def write(self) -> Path:
        path = self.dir / "report.md"
        path.write_text("\n".join(self.lines))
        return path


def register_onto(points: np.ndarray, s: np.ndarray, truth: np.ndarray, truth_s: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """A reconstruction (p, 3) at arc lengths ``s`` rigidly registered onto the truth (k, 3) at ``truth_s`` (Kabsch
    on arc-length correspondences), and each registered point's distance from the truth polyline (p,), m."""
    from twin import metrics

    at_s = np.stack([np.interp(s, truth_s, truth[:, j]) for j in range(3)], axis=-1)
    if not np.all(np.isfinite(points)):
        return np.full_like(points, np.nan), np.full(len(points), np.nan)
    r, t = metrics.kabsch(points, at_s)
    registered = points @ r.T + t
    return registered, metrics.point_to_polyline(registered, truth)


def overlay_panels(names: Sequence[str], truth: np.ndarray, truth_s: np.ndarray, recon: Mapping[str, np.ndarray],
                   s: np.ndarray, fixture: np.ndarray | None = None) -> tuple[list[dict], dict[str, np.ndarray]]:
    """Panels for :func:`shape_overlays` and the errors along the arc length, from stacks of curves.

    ``truth`` (k, m, 3) at ``truth_s``; ``recon`` label → (k, p, 3) at ``s``, each registered onto its truth
    (:func:`register_onto`); ``fixture`` (k, f, 3) or None. Returns the panels (the note: the first label's max
    error) and, per label, the distances (k, p) in m."""
    along: dict[str, np.ndarray] = {}
    registered: dict[str, list] = {}
    for label, curves in recon.items():
        pairs = [register_onto(c, s, t, truth_s) for c, t in zip(curves, truth, strict=True)]
        registered[label] = [p[0] for p in pairs]
        along[label] = np.stack([p[1] for p in pairs])
    first = next(iter(recon), None)
    panels = []
    for i, name in enumerate(names):
        note = f"max {np.nanmax(along[first][i]) * 1e3:.2f} mm ({LABELS.get(first, first)})" if first else ""
        panels.append({"name": name, "truth": truth[i], "recon": {k: v[i] for k, v in registered.items()},
                       "fixture": None if fixture is None else fixture[i], "note": note})
    return panels, along


def error_over_time(t: np.ndarray, series_mm: Mapping[str, np.ndarray], ylabel: str = "max error (mm)",
                    marks: np.ndarray | None = None, mark_label: str = "peaks lost"):
    """Error curves over time, one per label; ``marks`` (bool per sample) shades where something happened."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 3.2))
    for label, y in series_mm.items():
        ax.plot(t, y, label=label, lw=1.2)
    if marks is not None and np.any(marks):
        ax.fill_between(t, 0, 1, where=marks, transform=ax.get_xaxis_transform(), color="0.85",
                        label=mark_label, step="mid")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def tip_trajectories(truth_mm: np.ndarray, recon_mm: Mapping[str, np.ndarray], title: str = "tip trajectory"):
    """Tip positions (n, 3) in mm, truth and reconstructions, in the two planes of largest motion."""
    plt = pyplot()
    centred = truth_mm - truth_mm.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    axes = vt[:2] if np.linalg.matrix_rank(centred) >= 2 else np.eye(3)[:2]
    fig, ax = plt.subplots(figsize=(5, 5))
    origin = truth_mm.mean(axis=0)

    def proj(p):
        return (p - origin) @ axes.T

    tp = proj(truth_mm)
    ax.plot(tp[:, 0], tp[:, 1], "k-", lw=2, label="truth", alpha=0.6)
    for label, p in recon_mm.items():
        q = proj(p)
        ax.plot(q[:, 0], q[:, 1], lw=1, label=label)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("mm (first principal direction)")
    ax.set_ylabel("mm (second principal direction)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def curvature_profiles(grating_s: np.ndarray, truth: np.ndarray, recon: Mapping[str, np.ndarray],
                       title: str = "curvature along the fibre"):
    """k_x and k_y (1/m) at the gratings, truth vs reconstructions; s in m (plotted in mm)."""
    plt = pyplot()
    fig, axs = plt.subplots(1, 2, figsize=(9, 3.2), sharex=True)
    for j, name in enumerate(("k_x", "k_y")):
        ax = axs[j]
        ax.plot(grating_s * 1e3, truth[:, j], "k-o", ms=3, label="truth", alpha=0.7)
        for label, k in recon.items():
            ax.plot(grating_s * 1e3, k[:, j], "--.", label=label)
        ax.set_xlabel("arc length (mm)")
        ax.set_ylabel(f"{name} (1/m)")
        ax.grid(alpha=0.3)
    axs[0].legend(fontsize=8)
    fig.suptitle(title)
    return fig


def stamp(fig, calibration: str | None) -> None:
    """Write the calibration a figure was made with under it (once)."""
    if calibration and not getattr(fig, "_calibration_stamped", False):
        fig.text(0.01, 0.005, calibration, fontsize=7, color="0.35", ha="left", va="bottom")
        fig._calibration_stamped = True


def _plane(points: np.ndarray) -> np.ndarray:
    """The two directions (2, 3) of largest spread of ``points`` (n, 3): the view that shows a shape best."""
    centred = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    return vt[:2]


def shape_overlays(panels: Sequence[Mapping], title: str, calibration: str | None = None, columns: int = 4):
    """One panel per shape: ``truth`` (black), ``fixture`` (grey, dashed, optional) and each reconstruction in
    ``recon`` (label → points) drawn in mm in the plane of the truth's largest spread.

    ``panels``: mappings with ``name``, ``truth`` (k, 3) m, ``recon`` {label: (p, 3) m} and optionally
    ``fixture`` (m, 3) m and ``note`` (a line under the name, e.g. the max error). Labels that are pipeline modes
    (``default``, ``paper``, ``paper-literal``) get their fixed colours."""
    plt = pyplot()
    n = max(1, len(panels))
    cols = min(columns, n)
    rows = int(np.ceil(n / cols))
    fig, axs = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.2 * rows + 0.6), squeeze=False)
    for ax in axs.ravel()[n:]:
        ax.set_visible(False)
    for ax, panel in zip(axs.ravel(), panels, strict=False):
        truth = np.asarray(panel["truth"]) * 1e3
        basis = _plane(truth)
        origin = truth[0]

        def proj(p, basis=basis, origin=origin):
            return (np.asarray(p) * 1e3 - origin) @ basis.T

        if panel.get("fixture") is not None:
            f = proj(panel["fixture"])
            ax.plot(f[:, 0], f[:, 1], ls="--", color="0.6", lw=2.5, label="fixture")
        t = proj(panel["truth"])
        ax.plot(t[:, 0], t[:, 1], color="k", lw=1.6, label="truth (catheter)")
        for k, (label, pts) in enumerate(panel["recon"].items()):
            q = proj(pts)
            ax.plot(q[:, 0], q[:, 1], color=COLOURS.get(label, f"C{k + 4}"), lw=1.0, ls="-" if k == 0 else ":",
                    label=LABELS.get(label, label))
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(panel["name"] + (f"\n{panel['note']}" if panel.get("note") else ""), fontsize=8)
        ax.set_xlabel("mm", fontsize=7)
        ax.set_ylabel("mm", fontsize=7)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    handles, labels = axs.ravel()[0].get_legend_handles_labels()
    fig.suptitle(title, fontsize=10, y=0.995)
    fig.tight_layout(rect=(0, 0.03, 1, 1 - 0.75 / fig.get_figheight()))
    fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 1 - 0.3 / fig.get_figheight()), fontsize=7,
               ncol=len(labels), frameon=False)
    stamp(fig, calibration)
    return fig


def error_along_arc(s: np.ndarray, errors_mm: Mapping[str, np.ndarray], title: str, calibration: str | None = None,
                    paper_max_mm: float | None = None, ylabel: str = "distance to the truth (mm)"):
    """Error along the arc length, one line per label (e.g. per shape); ``s`` in m, errors in mm; the paper's max
    as a dashed reference line when given."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 3.4))
    for k, (label, e) in enumerate(errors_mm.items()):
        ax.plot(np.asarray(s) * 1e3, e, lw=1.1, label=label, color=f"C{k % 10}", ls="-" if k < 10 else "--")
    if paper_max_mm is not None:
        ax.axhline(paper_max_mm, color="k", lw=0.8, ls="--", label=f"the paper: max {paper_max_mm:g} mm")
    ax.set_xlabel("arc length from the fibre's base (mm)")
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    stamp(fig, calibration)
    return fig


def per_shape_errors(names: Sequence[str], max_mm: Mapping[str, Sequence[float]],
                     mean_mm: Mapping[str, Sequence[float]] | None, title: str, calibration: str | None = None,
                     paper_max_mm: float | None = None, paper_mean_mm: float | None = None,
                     xlabel: str = "shape", log: bool | None = None, ylabel: str = "max error (mm)"):
    """Max (and mean) error per shape, one bar per label, the paper's figures as dashed reference lines.

    ``log``: logarithmic axis; by default when the largest bar is 30× the smallest."""
    plt = pyplot()
    panels = [(ylabel, max_mm, paper_max_mm)]
    if mean_mm is not None:
        panels.append(("mean error (mm)", mean_mm, paper_mean_mm))
    fig, axs = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 3.6), squeeze=False)
    x = np.arange(len(names))
    for ax, (ylabel, values, paper) in zip(axs[0], panels, strict=True):
        width = 0.8 / max(1, len(values))
        for k, (label, v) in enumerate(values.items()):
            ax.bar(x + (k - (len(values) - 1) / 2) * width, v, width, label=LABELS.get(label, label),
                   color=COLOURS.get(label, f"C{k + 4}"))
        if paper is not None:
            ax.axhline(paper, color="k", lw=0.9, ls="--", label=f"the paper (hardware): {paper:g} mm")
        flat = np.concatenate([np.asarray(v, float).ravel() for v in values.values()])
        flat = flat[np.isfinite(flat) & (flat > 0)]
        use_log = log if log is not None else (flat.size and flat.max() > 30 * flat.min())
        if use_log:
            ax.set_yscale("log")
        ax.set_xticks(x, list(names), rotation=45, ha="right", fontsize=7)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3, axis="y")
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.03, 1, 0.97))
    stamp(fig, calibration)
    return fig
