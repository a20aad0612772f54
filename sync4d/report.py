"""Plain-text tables and plots for command output."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["align_table", "plot_object_trajectories"]


def align_table(
    header: Sequence[str], rows: Sequence[Sequence[str]], left: Sequence[int] = (0,)
) -> str:
    """Columns padded to a common width under a dashed rule; columns in `left` are
    left-aligned, the rest right-aligned (numbers)."""
    lines = [list(header)] + [list(r) for r in rows]
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    out = []
    for j, line in enumerate(lines):
        cells = [
            c.ljust(w) if i in left else c.rjust(w)
            for i, (c, w) in enumerate(zip(line, widths, strict=True))
        ]
        out.append("  ".join(cells).rstrip())
        if j == 0:
            out.append("  ".join("-" * w for w in widths))
    return "\n".join(out)


def plot_object_trajectories(
    export: dict, names: dict[int, str], path: Path, title: str = "object centroids"
) -> Path:
    """Three panels (world x, y, z against time) with one line per object: the centroid of
    each object's Gaussians from a Phase 2 motion export (`centroids` [K, T, 3], `times` [T]);
    label 0 (background) is left out. Writes a PNG to `path` and returns it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cent = np.asarray(export["centroids"])
    times = np.asarray(export["times"])
    labels = np.asarray(export["labels"])
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.4), dpi=110, sharex=True)
    drawn = 0
    for k in range(1, cent.shape[0]):
        if not (labels == k).any():
            continue
        drawn += 1
        name = names.get(k, f"object {k}")
        # Objects named by colour ("red ball") are drawn in that colour.
        colour = next((w for w in name.split() if matplotlib.colors.is_color_like(w)), None)
        for axis, ax in enumerate(axes):
            ax.plot(times, cent[k, :, axis], lw=1.5, label=name, color=colour)
    for axis, ax in enumerate(axes):
        ax.set_xlabel("time")
        ax.set_ylabel(f"centroid {'xyz'[axis]} (world units)")
        ax.grid(alpha=0.3)
    if drawn:
        axes[0].legend(fontsize=8)
    else:
        axes[1].text(0.5, 0.5, "no objects assigned", ha="center", transform=axes[1].transAxes)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_query_timeline(answer: dict, path: Path) -> Path:
    """One row per object of a query answer (`sync4d.phase3.query.answer`): its per-frame
    score curve against time with the active frames shaded, objects in ranked order. Writes a
    PNG to `path` and returns it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    times = np.asarray(answer["times"])
    objects = answer["objects"]
    n = max(1, len(objects))
    fig, axes = plt.subplots(n, 1, figsize=(8, 1.1 + 1.0 * n), dpi=110, sharex=True,
                             squeeze=False)  # fmt: skip
    for ax, obj in zip(axes[:, 0], objects, strict=False):
        name = obj["name"]
        colour = next((w for w in name.split() if matplotlib.colors.is_color_like(w)), None)
        curve = np.asarray(answer["timeline"][name])
        active = np.asarray(answer["active"][name], dtype=bool)
        ax.plot(times, curve, lw=1.5, color=colour or "C0")
        lo, hi = float(np.min(curve)), float(np.max(curve))
        ax.fill_between(times, lo, hi, where=active, step="mid", alpha=0.25,
                        color=colour or "C0", linewidth=0)  # fmt: skip
        ax.set_ylabel(f"{name}\n{obj['score']:.3f}", rotation=0, ha="right", va="center",
                      fontsize=8)  # fmt: skip
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("time")
    fig.suptitle(f"\"{answer['query']}\" ({answer['scorer']} scorer; shaded: active)",
                 fontsize=10)  # fmt: skip
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
