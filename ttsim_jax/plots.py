"""Matplotlib figures (PNG) of trajectories over the table."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _table(ax_top, ax_side, table_length=2.74, table_width=1.525, net_height=0.1525):
    hl, hw = table_length / 2, table_width / 2
    ax_top.add_patch(__import__("matplotlib.patches", fromlist=["Rectangle"]).Rectangle(
        (-hl, -hw), table_length, table_width, facecolor="#1f4e79", alpha=0.25, edgecolor="#1f4e79"))
    ax_top.plot([0, 0], [-hw - 0.15, hw + 0.15], color="k", lw=1.5)
    ax_top.plot([-hl, hl], [0, 0], color="white", lw=0.8)
    ax_side.plot([-hl, hl], [0, 0], color="#1f4e79", lw=3)
    ax_side.plot([0, 0], [0, net_height], color="k", lw=1.5)


def plot_trajectories(positions, path, labels=None, events=None, title="", max_balls=60):
    """Top and side views of ball paths over the table.

    Arguments:
        positions: (B, N, 3) recorded positions [m] (world frame).
        path: PNG file to write.
        labels: optional (B,) names (e.g. shot types) used to colour and label the paths.
        events: optional (B, K, 3) event positions and (B, K) kinds as a tuple, drawn as markers.
        title: figure title.
        max_balls: at most this many paths are drawn.

    Returns:
        The path written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    positions = np.asarray(positions)[:max_balls]
    fig, (ax_top, ax_side) = plt.subplots(2, 1, figsize=(10, 8), gridspec_kw={"height_ratios": [1.1, 1]})
    _table(ax_top, ax_side)
    names = None if labels is None else np.asarray(labels)[:max_balls]
    colours = {}
    cmap = plt.get_cmap("tab10")
    for i, p in enumerate(positions):
        keep = np.isfinite(p).all(-1) & (p[:, 2] > -0.76)
        name = None if names is None else str(names[i])
        if name not in colours:
            colours[name] = cmap(len(colours) % 10)
        first = name is not None and not any(str(n) == name for n in (names[:i] if names is not None else []))
        ax_top.plot(p[keep, 0], p[keep, 1], color=colours[name], lw=0.8, alpha=0.8, label=name if first else None)
        ax_side.plot(p[keep, 0], p[keep, 2], color=colours[name], lw=0.8, alpha=0.8)
    if events is not None:
        epos, kinds = (np.asarray(e)[:max_balls] for e in events)
        for kind, marker, colour in ((1, "o", "k"), (2, "s", "red"), (3, "x", "orange")):
            sel = kinds == kind
            ax_top.scatter(epos[sel][:, 0], epos[sel][:, 1], s=10, marker=marker, color=colour, zorder=3)
            ax_side.scatter(epos[sel][:, 0], epos[sel][:, 2], s=10, marker=marker, color=colour, zorder=3)
    ax_top.set(xlabel="x [m] (along the table)", ylabel="y [m]", aspect="equal", xlim=(-3.5, 3.5), ylim=(-1.6, 1.6))
    ax_side.set(xlabel="x [m]", ylabel="z [m] (above the table surface)", xlim=(-3.5, 3.5), ylim=(-0.8, 2.0))
    ax_top.set_title(title or "ball paths: top view (dots: bounces, squares: racket, x: net)")
    if names is not None:
        ax_top.legend(loc="upper left", fontsize=7, ncol=4)
    ax_side.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
