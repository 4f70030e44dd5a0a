"""Figures shared by the sections: a matplotlib figure with the stamp, and the work-precision diagram
(error against time, one curve per knob, the exact reference as a star, defaults circled)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path


def figure(ncols: int, nrows: int = 1, width: float = 6.0, height: float = 4.4):
    """(pyplot, figure, flat axes) on the Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(nrows, ncols, figsize=(width * ncols, height * nrows + 0.4), squeeze=False)
    return plt, fig, axes.ravel()


def save(plt, fig, path: Path, title: str, stamp: str, bottom: float = 0.03) -> None:
    """Title, the stamp line at the bottom, write the PNG and close the figure."""
    fig.suptitle(title, fontsize=12)
    fig.text(0.01, 0.005, stamp, fontsize=7, color="0.35")
    fig.tight_layout(rect=(0, bottom, 1, 0.97))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_work_precision(
    points: list[dict],
    panels: Sequence[tuple[str, str]],
    path: Path,
    title: str,
    stamp: str,
    xlabel: str = "median time per query (ms)",
    xscale: float = 1.0,
    log_error: bool = True,
    by_time: bool = False,
) -> None:
    """One panel per error measure: error against time, a line per curve (knob, points in the order they
    were measured, or by time), the exact reference as a black star, defaults circled (thin circles: a
    knob's default value at reduced settings). Errors on a symlog axis so that 0 is drawn."""
    plt, fig, axes = figure(len(panels))
    curves = list(dict.fromkeys(p["curve"] for p in points))
    colours = plt.get_cmap("tab10")
    for ax, (key, label) in zip(axes, panels, strict=True):
        seen = set()
        for ci, curve in enumerate(curves):
            pts = [p for p in points if p["curve"] == curve]
            if by_time:
                pts.sort(key=lambda p: p["time_ms"])
            x = [p["time_ms"] * xscale for p in pts]
            y = [p["errors"][key] for p in pts]
            ax.plot(x, y, "o-", color=colours(ci % 10), label=curve, ms=5, lw=1.4, alpha=0.9)
            for p, xi, yi in zip(pts, x, y, strict=True):
                if (p["label"], xi) not in seen:
                    seen.add((p["label"], xi))
                    ax.annotate(p["label"], (xi, yi), fontsize=6, xytext=(3, 3), textcoords="offset points")
                if p["default"] or p["info"].get("default_value"):
                    ax.plot(xi, yi, "o", ms=12, mfc="none", mec="black", mew=1.2 if p["default"] else 0.5)
        for p in points:
            if p["exact"]:
                ax.plot(p["time_ms"] * xscale, p["errors"][key], "*", ms=16, color="black", zorder=5)
        pos = [p["errors"][key] for p in points if p["errors"][key] > 0]
        if log_error and pos:
            t = min(pos) / 2
            ax.set_yscale("symlog", linthresh=t)
            ax.set_yticks(
                [0.0]
                + [10.0**k for k in range(math.ceil(math.log10(t)), math.ceil(math.log10(max(pos))) + 1)]
            )
        ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    ax = axes[0]
    if any(p["exact"] for p in points):
        ax.plot([], [], "*", color="black", ms=12, label="exact reference (error 0)")
    if any(p["default"] for p in points):
        ax.plot([], [], "o", ms=10, mfc="none", mec="black", mew=1.2, label="default")
    if any(p["info"].get("default_value") and not p["default"] for p in points):
        ax.plot([], [], "o", ms=10, mfc="none", mec="black", mew=0.5, label="knob at its default value")
    fig.legend(
        *ax.get_legend_handles_labels(),
        loc="lower center",
        ncol=5,
        fontsize=8,
        frameon=False,
        bbox_to_anchor=(0.5, 0.03),
    )
    save(plt, fig, path, title, stamp, bottom=0.16)
