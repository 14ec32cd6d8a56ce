"""Matplotlib figures (PNG) of trajectories over the table."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ttsim_jax.physics.dimensions import FLOOR_Z, NET_HEIGHT, TABLE_LENGTH, TABLE_WIDTH


def draw_table(ax_top, ax_side, table_length=TABLE_LENGTH, table_width=TABLE_WIDTH, net_height=NET_HEIGHT):
    """The table, its centre line and the net in a top (x, y) and a side (x, z) view [m]."""
    from matplotlib.patches import Rectangle

    hl, hw = table_length / 2, table_width / 2
    ax_top.add_patch(Rectangle((-hl, -hw), table_length, table_width, facecolor="#1f4e79", alpha=0.25,
                               edgecolor="#1f4e79"))
    ax_top.plot([0, 0], [-hw - 0.15, hw + 0.15], color="k", lw=1.5)
    ax_top.plot([-hl, hl], [0, 0], color="white", lw=0.8)
    ax_side.plot([-hl, hl], [0, 0], color="#1f4e79", lw=3)
    ax_side.plot([0, 0], [0, net_height], color="k", lw=2.5, zorder=4, solid_capstyle="butt")
    ax_side.annotate("net", (0, net_height), xytext=(4, 2), textcoords="offset points", fontsize=7)


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
    plt = pyplot()
    total = len(positions)
    positions = np.asarray(positions)[:max_balls]
    fig, (ax_top, ax_side) = plt.subplots(2, 1, figsize=(10, 8), gridspec_kw={"height_ratios": [1.1, 1]})
    draw_table(ax_top, ax_side)
    names = None if labels is None else np.asarray(labels)[:max_balls]
    colours = {}
    cmap = plt.get_cmap("tab10")
    for i, p in enumerate(positions):
        keep = np.isfinite(p).all(-1) & (p[:, 2] > FLOOR_Z)
        name = None if names is None else str(names[i])
        if name not in colours:
            colours[name] = cmap(len(colours) % 10)
        first = name is not None and not any(str(n) == name for n in (names[:i] if names is not None else []))
        ax_top.plot(p[keep, 0], p[keep, 1], color=colours[name], lw=0.8, alpha=0.8, label=name if first else None)
        ax_side.plot(p[keep, 0], p[keep, 2], color=colours[name], lw=0.8, alpha=0.8)
    if events is not None:
        epos, kinds = (np.asarray(e)[:max_balls] for e in events)
        for kind, marker, colour, what in ((1, "o", "k", "table bounce"), (2, "s", "red", "racket contact"),
                                           (3, "x", "orange", "net contact")):
            sel = kinds == kind
            ax_top.scatter(epos[sel][:, 0], epos[sel][:, 1], s=10, marker=marker, color=colour, zorder=3)
            ax_side.scatter(epos[sel][:, 0], epos[sel][:, 2], s=10, marker=marker, color=colour, zorder=3,
                            label=what if sel.any() else None)
        if (kinds > 0).any():
            ax_side.legend(loc="upper right", fontsize=7, title="events", title_fontsize=7)
    ax_top.set(xlabel="x [m] (along the table)", ylabel="y [m]", aspect="equal", xlim=(-3.5, 3.5), ylim=(-1.6, 1.6))
    ax_side.set(xlabel="x [m]", ylabel="z [m] (above the table surface)", xlim=(-3.5, 3.5), ylim=(-0.8, 2.0))
    drawn = f"{len(positions)} of {total} paths drawn" if total > len(positions) else f"{total} paths"
    ax_top.set_title(f"{title} ({drawn})" if title else f"ball paths, top view ({drawn})")
    ax_side.set_title("side view", fontsize=9)
    if names is not None:
        ax_top.legend(loc="upper left", fontsize=7, ncol=4, title="shot type" if len(colours) > 1 else None,
                      title_fontsize=7)
    ax_side.grid(alpha=0.3)
    return save_figure(fig, path)


#: Colours of the paper's figures per model family (others: the tab10 cycle).
MODEL_COLOURS = {"nakashima2011": "#1f77b4", "durr2026": "#ff7f0e", "conti2026": "#c51b8a"}


def model_colours(names) -> dict:
    """A colour per model name: the paper's for its three models, the tab10 cycle for the others."""
    import matplotlib.pyplot as plt

    cmap = plt.get_cmap("tab10")
    others = [n for n in names if n not in MODEL_COLOURS]
    return {n: MODEL_COLOURS.get(n) or cmap((2 + others.index(n)) % 10) for n in names}


def pyplot():
    """``matplotlib.pyplot`` on the non-interactive Agg backend (figures are only written to files).

    Returns:
        The ``matplotlib.pyplot`` module.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path, *, tight: bool = True) -> Path:
    """Writes a figure as PNG (its folder made if missing) and closes it.

    Arguments:
        fig: the matplotlib figure.
        path: the PNG file to write.
        tight: fit the panels' spacing to their labels (``tight_layout``: a draw of its own, a
            second or more for a grid of dozens of panels; pass False where the caller set the
            spacing).

    Returns:
        The path written.
    """
    import io

    from ttsim_jax.files.atomic import atomic_write

    path = Path(path)
    buf = io.BytesIO()
    try:
        if tight:
            fig.tight_layout()
        fig.savefig(buf, format=path.suffix.lstrip(".").lower() or "png", dpi=110)
    finally:
        pyplot().close(fig)
    # drawn in memory, written whole: a full disk leaves no truncated figure (nor a previous one broken)
    atomic_write(path, buf.getvalue(), "a figure")
    return path


def plot_violins(groups: dict, path, ylabel: str = "", title: str = "", panels=None) -> Path:
    """Violin plots of several models' values side by side, per category.

    Arguments:
        groups: {category: {model: (n,) values}}; NaN values are left out, a model without values
            in a category leaves a gap. Medians are marked.
        path: PNG file to write.
        ylabel, title: labels.
        panels: optional sequence of category lists, one subplot (row) each (default: one panel).

    Returns:
        The path written.
    """
    plt = pyplot()
    cats = list(groups)
    panels = [cats] if panels is None else [list(p) for p in panels]
    names = list(dict.fromkeys(n for g in groups.values() for n in g))
    colours = model_colours(names)
    fig, axes = plt.subplots(len(panels), 1, figsize=(max(6.0, 1.2 * len(names) * max(map(len, panels))), 3.6 * len(panels)),
                             squeeze=False)
    width = 0.8 / max(len(names), 1)
    for ax, panel in zip(axes[:, 0], panels):
        for i, cat in enumerate(panel):
            for j, name in enumerate(names):
                v = np.asarray(groups[cat].get(name, []), np.float64)
                v = v[np.isfinite(v)]
                x = i + (j - (len(names) - 1) / 2) * width
                if len(v) > 1 and np.ptp(v) > 0:
                    body = ax.violinplot(v, positions=[x], widths=0.9 * width, showextrema=False)["bodies"][0]
                    body.set_facecolor(colours[name])
                    body.set_alpha(0.6)
                if len(v):
                    ax.scatter([x], [np.median(v)], color="k", s=12, zorder=3)
        ax.set_xticks(range(len(panel)), [str(c) for c in panel])
        ax.axhline(0.0, color="grey", lw=0.6)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3, axis="y")
    for name in names:
        axes[0, 0].plot([], [], color=colours[name], lw=6, alpha=0.6, label=name)
    axes[0, 0].legend(fontsize=8, ncol=min(len(names), 4))
    axes[0, 0].set_title(title + " (dots: medians)")
    return save_figure(fig, path)


def plot_landing(errors: dict, landing: dict, measured, hist_path, xy_path, max_points: int = 2000) -> tuple:
    """The landing-error figures: a histogram of the error distance per model, and the
    predicted and measured landing points over the table (one panel per model).

    Arguments:
        errors: {model: (N,) landing error [m]} (NaN: no simulated landing).
        landing: {model: (N, 2) simulated landing points}; measured: (N, 2) measured ones.
        hist_path, xy_path: PNG files to write.
        max_points: at most this many points per panel of the XY figure.

    Returns:
        (histogram path, XY path).
    """
    plt = pyplot()
    names = list(errors)
    colours = model_colours(names)
    finite = [np.asarray(e)[np.isfinite(e)] for e in errors.values()]
    top = max([float(np.percentile(e, 99)) for e in finite if len(e)] + [0.05])
    bins = np.linspace(0.0, top, 40)
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, e in zip(names, finite):
        label = f"{name} (median {np.median(e):.3f} m)" if len(e) else name
        ax.hist(np.clip(e, 0.0, top), bins=bins, histtype="step", lw=1.6, color=colours[name], label=label)
    ax.set(xlabel="landing-position error [m]", ylabel="contacts", title="landing-position error (last bin: and above)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    hist_path = save_figure(fig, hist_path)

    measured = np.asarray(measured)[:max_points]
    fig, axes = plt.subplots(1, len(names), figsize=(5.2 * len(names), 4.2), squeeze=False)
    for ax, name in zip(axes[0], names):
        side = plt.figure().add_subplot()  # draw_table draws a top and a side view; only the top is kept
        draw_table(ax, side)
        plt.close(side.figure)
        p = np.asarray(landing[name])[:max_points]
        ax.scatter(measured[:, 0], measured[:, 1], s=6, color="k", alpha=0.5, label="measured")
        ax.scatter(p[:, 0], p[:, 1], s=6, color=colours[name], alpha=0.6, label=f"{name}")
        ax.set(xlabel="x [m]", ylabel="y [m]", aspect="equal", xlim=(-2.0, 2.0), ylim=(-1.2, 1.2))
        ax.set_title(f"landing points: {name}")
        ax.legend(fontsize=7, loc="upper left")
    return hist_path, save_figure(fig, xy_path)


def plot_predicted_vs_measured(panels: dict, path, *, xlabel: str = "measured", ylabel: str = "predicted",
                               title: str = "", max_points: int = 1500) -> Path:
    """Scatter of predicted against measured values per panel and model, with the identity line.

    Arguments:
        panels: {panel title: (measured (n,), {model: predicted (n,)})}; one subplot each.
        path: PNG file to write.
        xlabel, ylabel, title: labels.
        max_points: at most this many points per panel (an even subsample), so the file stays light.

    Returns:
        The path written.
    """
    plt = pyplot()
    names = list(dict.fromkeys(n for _, pred in panels.values() for n in pred))
    colours = model_colours(names)
    cols = min(len(panels), 3)
    rows = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 4.0 * rows), squeeze=False)
    for ax, (label, (measured, pred)) in zip(axes.ravel(), panels.items()):
        measured = np.asarray(measured, np.float64)
        keep = np.linspace(0, len(measured) - 1, min(len(measured), max_points)).astype(int) if len(measured) else []
        lo, hi = (float(np.min(measured)), float(np.max(measured))) if len(measured) else (0.0, 1.0)
        for name in names:
            if name in pred:
                ax.scatter(measured[keep], np.asarray(pred[name], np.float64)[keep], s=4, alpha=0.4,
                           color=colours[name], label=name)
        ax.plot([lo, hi], [lo, hi], color="k", lw=0.8)
        ax.set_title(f"{label} (n={len(measured)})", fontsize=9)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(panels):]:
        ax.set_visible(False)
    axes[0, 0].legend(fontsize=7, markerscale=3)
    fig.suptitle(title)
    return save_figure(fig, path)
