"""PNG figures for the report (matplotlib Agg canvas, no pyplot global state).

Each function returns the written path, or None when there is nothing to draw. MSE levels are
never put on one axis across backbones: every backbone x suite gets its own panel and y axis.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from bench.analysis.agreement import is_defined
from bench.analysis.rankings import PRIMARY, Ranking, backbone_order
from bench.analysis.transfer import Transfer
from bench.grid.kinds import CELL_KINDS, column_label


def _figure(n_panels: int, width: float = 4.2, height: float = 3.4):
    cols = min(n_panels, 2)
    rows = math.ceil(n_panels / cols)
    fig = Figure(figsize=(width * cols, height * rows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax in axes[n_panels:]:
        ax.set_visible(False)
    return fig, axes


def plot_mse_intervals(rankings: Sequence[Ranking], path: Path) -> Path | None:
    """One panel per backbone x suite: mean normalised MSE per encoder with its 95% interval."""
    panels = [r for r in rankings if r.encoders]
    if not panels:
        return None
    fig, axes = _figure(len(panels))
    for ax, r in zip(axes, panels):
        names = [e.encoder for e in r.encoders]
        means = np.array([e.mean[PRIMARY] for e in r.encoders])
        lo = np.array([e.ci[PRIMARY][0] for e in r.encoders])
        hi = np.array([e.ci[PRIMARY][1] for e in r.encoders])
        err = np.vstack([np.nan_to_num(means - lo), np.nan_to_num(hi - means)])
        colors = ["tab:blue" if e.in_top_tier else "tab:gray" for e in r.encoders]
        x = np.arange(len(names))
        ax.bar(x, means, color=colors, alpha=0.6)
        ax.errorbar(x, means, yerr=err, fmt="none", ecolor="black", capsize=3)
        for e_i, e in enumerate(r.encoders):
            seeds = list(e.per_seed[PRIMARY].values())
            ax.scatter([e_i] * len(seeds), seeds, color="black", s=10, zorder=3)
        ax.set_xticks(x, names, rotation=30, ha="right")
        ax.set_title(f"{r.backbone} x {r.suite} (blue: top tier)", fontsize=9)
        ax.set_ylabel("normalised MSE (own axis)")
    fig.suptitle("Offline action MSE per encoder, 95% intervals (releases, seeds, episodes, "
                 "windows drawn), dots = cells\n"
                 "levels are not comparable across backbones", fontsize=9)
    fig.savefig(path, dpi=110)
    return path


def plot_rank_bump(transfers: Sequence[Transfer], path: Path) -> Path | None:
    """One panel per suite and backbone pair: each encoder's rank on the two backbones."""
    panels = [t for t in transfers if t.complete]
    if not panels:
        return None
    fig, axes = _figure(len(panels), width=3.6)
    for ax, t in zip(axes, panels):
        for enc in t.encoders:
            ranks = [t.small_ranks[enc], t.large_ranks[enc]]
            ax.plot([0, 1], ranks, marker="o")
            ax.annotate(enc, (0, ranks[0]), xytext=(-6, 0), textcoords="offset points",
                        ha="right", va="center", fontsize=8)
            ax.annotate(enc, (1, ranks[1]), xytext=(6, 0), textcoords="offset points",
                        ha="left", va="center", fontsize=8)
        n = max(list(t.small_ranks.values()) + list(t.large_ranks.values()))
        ax.set_ylim(n + 0.5, 0.5)
        ax.set_yticks(range(1, n + 1))
        ax.set_xlim(-0.8, 1.8)
        ax.set_xticks([0, 1], [t.small, t.large])
        tau = t.agreement.get("tau_b", float("nan"))
        ax.set_title(f"{t.suite}: rank 1 = lowest MSE, tau-b = {tau:.2f}", fontsize=9)
        ax.set_ylabel("rank")
    fig.savefig(path, dpi=110)
    return path


def plot_horizon_curves(records: Sequence[dict], path: Path) -> Path | None:
    """One panel per backbone x suite: normalised MSE per action-chunk step, mean over seeds."""
    groups: dict[tuple[str, str], dict[str, list[list[float]]]] = {}
    for r in records:
        curve = r.scores.per_horizon_in(PRIMARY)
        label = column_label(r)
        if not curve or label is None:
            continue
        groups.setdefault((r.backbone, r.suite), {}).setdefault(label, []).append(curve)
    if not groups:
        return None
    fig, axes = _figure(len(groups))
    order = backbone_order([b for b, _ in groups])
    panels = sorted(groups.items(), key=lambda kv: (kv[0][1], order.index(kv[0][0])))
    native_columns = {k.name for k in CELL_KINDS.values() if k.encoder == "none"}
    for ax, ((backbone, suite), curves) in zip(axes, panels):
        for label, runs in sorted(curves.items()):
            length = min(len(c) for c in runs)
            mean = np.mean([c[:length] for c in runs], axis=0)
            style = "--" if label in native_columns else "-"
            ax.plot(np.arange(1, length + 1), mean, style, label=label)
        ax.set_title(f"{backbone} x {suite}", fontsize=9)
        ax.set_xlabel("action-chunk step")
        ax.set_ylabel("normalised MSE (own axis)")
        ax.legend(fontsize=7)
    fig.suptitle("Per-horizon error (mean over seeds); levels not comparable across backbones",
                 fontsize=9)
    fig.savefig(path, dpi=110)
    return path


def plot_closed_loop(closed_loop: Sequence, path: Path) -> Path | None:
    """One panel per backbone x suite: success rate (Wilson interval) against offline MSE."""
    panels = [c for c in closed_loop if c.items]
    if not panels:
        return None
    fig, axes = _figure(len(panels))
    for ax, c in zip(axes, panels):
        succ = np.array(c.success)
        lo = np.array([ci[0] for ci in c.success_ci])
        hi = np.array([ci[1] for ci in c.success_ci])
        err = np.vstack([np.nan_to_num(succ - lo), np.nan_to_num(hi - succ)])
        ax.errorbar(c.mse, succ, yerr=err, fmt="o", capsize=3)
        for x, y, name in zip(c.mse, succ, c.items):
            ax.annotate(name, (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
        tau = c.agreement.get("tau_b")
        ax.set_title(f"{c.backbone} x {c.suite}: tau-b "
                     f"{'n/a' if tau is None or not is_defined(tau) else f'{tau:.2f}'}",
                     fontsize=9)
        ax.set_xlabel("offline normalised MSE (lower is better)")
        ax.set_ylabel("closed-loop success")
        ax.set_ylim(-0.05, 1.05)
    fig.suptitle("Closed-loop success vs offline MSE (95% Wilson intervals)", fontsize=9)
    fig.savefig(path, dpi=110)
    return path


def plot_proxy_scatter(panels: Sequence[tuple[str, list, list, list]],
                       path: Path) -> Path | None:
    """One panel per (backbone x suite: proxy): each encoder's proxy score (x, higher is better)
    against its graft MSE (y, lower is better). panels: bench.report.screen.scatter_points."""
    if not panels:
        return None
    fig, axes = _figure(len(panels), width=3.6, height=3.0)
    for ax, (title, scores, mse, names) in zip(axes, panels):
        ax.scatter(scores, mse, s=14)
        for x, y, name in zip(scores, mse, names):
            ax.annotate(name, (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("screen score (higher is better)")
        ax.set_ylabel("graft normalised MSE")
    fig.suptitle("Screen proxy vs graft MSE: a good screen slopes down", fontsize=9)
    fig.savefig(path, dpi=110)
    return path


def write_plots(rankings: Sequence[Ranking], transfers: Sequence[Transfer],
                records: Sequence[dict], out_dir: Path,
                closed_loop: Sequence = ()) -> list[tuple[str, Path]]:
    """Write every figure that has data into `out_dir`; returns [(title, path)]."""
    out_dir.mkdir(parents=True, exist_ok=True)
    jobs = [
        ("MSE per encoder with 95% intervals", "mse_by_encoder.png",
         lambda p: plot_mse_intervals(rankings, p)),
        ("Ranks between backbones (bump chart)", "rank_bump.png",
         lambda p: plot_rank_bump(transfers, p)),
        ("Per-horizon error curves", "per_horizon.png",
         lambda p: plot_horizon_curves(records, p)),
        ("Closed-loop success vs offline MSE", "closed_loop.png",
         lambda p: plot_closed_loop(closed_loop, p)),
    ]
    written = []
    for title, name, draw in jobs:
        path = draw(out_dir / name)
        if path is not None:
            written.append((title, path))
    return written
