"""`--report DIR` for any scenario: PNG plots and a short markdown summary a person reads instead of JSON.

A :class:`Report` collects paragraphs, tables and figures and writes ``DIR/report.md`` with the PNGs beside
it. The plot helpers cover what every experiment shows: errors over time, tip trajectories (truth vs
reconstruction) and curvature profiles along the fibre. Matplotlib runs headless (Agg).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

__all__ = ["Report", "curvature_profiles", "error_over_time", "pyplot", "register_onto", "tip_trajectories"]


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
    """

    def __init__(self, directory: str | Path, title: str):
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.lines = [f"# {title}", ""]

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
