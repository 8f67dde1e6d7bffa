"""Calibration report: the paper's Table 1 (markdown and CSV), RPE violin plots, per-view corrections, the view
predicted worst with its BBs."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from calib.result import CalibrationResult

#: the published results (Ma et al. 2022, Table 1), for side-by-side reports
PAPER_TABLE1: dict[str, dict[str, float]] = {
    "A": {
        "frames": 500,
        "bbs": 8,
        "elapsed_s": 60,
        "rpe_mean_mm": 0.065,
        "rpe_median_mm": 0.065,
        "rpe_std_mm": 0.0169,
        "s_per_frame": 0.12,
        "s_per_frame_per_bb": 0.015,
    },
    "B": {
        "frames": 656,
        "bbs": 16,
        "elapsed_s": 91,
        "rpe_mean_mm": 0.210,
        "rpe_median_mm": 0.201,
        "rpe_std_mm": 0.0377,
        "s_per_frame": 0.14,
        "s_per_frame_per_bb": 0.009,
    },
    "C": {
        "frames": 857,
        "bbs": 10,
        "elapsed_s": 208,
        "rpe_mean_mm": 0.490,
        "rpe_median_mm": 0.418,
        "rpe_std_mm": 0.370,
        "s_per_frame": 0.24,
        "s_per_frame_per_bb": 0.024,
    },
}

TABLE_ROWS = (
    ("Number of frames", "frames", "{:.0f}"),
    ("Number of BBs", "bbs", "{:.0f}"),
    ("Elapsed time (s)", "elapsed_s", "{:.3g}"),
    ("Mean RPE (mm)", "rpe_mean_mm", "{:.4f}"),
    ("Median RPE (mm)", "rpe_median_mm", "{:.4f}"),
    ("Std Dev RPE (mm)", "rpe_std_mm", "{:.4f}"),
    ("Time/frame (s)", "s_per_frame", "{:.3g}"),
    ("Time/frame/BB (s)", "s_per_frame_per_bb", "{:.3g}"),
)


PAPER_ITERATION = 2  # the published Table 1 reports the alternation after two iterations


def table1_row(result: CalibrationResult, iteration: int | None = None) -> dict[str, float]:
    """The paper's Table 1 figures for one calibration: RPE after ``iteration`` (default: the last for the
    bundle method, the second for the paper method, as the published table)."""
    if iteration is None:
        iteration = PAPER_ITERATION if result.method == "paper" else len(result.iterations) - 1
    last = result.iterations[min(iteration, len(result.iterations) - 1)]
    frames, bbs = result.n_frames, result.n_bbs
    return {
        "frames": frames,
        "bbs": bbs,
        "elapsed_s": result.elapsed_s,
        "rpe_mean_mm": last.rpe_mean_mm,
        "rpe_median_mm": last.rpe_median_mm,
        "rpe_std_mm": last.rpe_std_mm,
        "s_per_frame": result.elapsed_s / max(frames, 1),
        "s_per_frame_per_bb": result.elapsed_s / max(frames * bbs, 1),
    }


def markdown_table(columns: dict[str, dict[str, float]]) -> str:
    """A Table-1 style markdown table with one column per entry."""
    names = list(columns)
    lines = ["| | " + " | ".join(names) + " |", "| :--- |" + " :--- |" * len(names)]
    for label, key, fmt in TABLE_ROWS:
        cells = []
        for n in names:
            v = columns[n].get(key, float("nan"))
            cells.append(fmt.format(v) if np.isfinite(v) else "-")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_csv(path: Path, columns: dict[str, dict[str, float]]) -> None:
    """Table 1 as CSV: one row per figure, one column per entry."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["figure", *columns])
        for label, key, _ in TABLE_ROWS:
            w.writerow([label, *(columns[n].get(key, float("nan")) for n in columns)])


def violin_plot(path: Path, history: list[np.ndarray], title: str, max_iterations: int = 6) -> None:
    """Per-frame RPE distributions for the initial geometry and after each iteration (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    idx = list(range(len(history)))
    skipped = ""
    if len(idx) > max_iterations + 1:  # long LM runs: first few and the last, and the figure says so
        skipped = (
            f" (iterations {max_iterations}-{idx[-1] - 1} not shown)"
            if idx[-1] - 1 > max_iterations
            else f" (iteration {max_iterations} not shown)"
        )
        idx = idx[:max_iterations] + [idx[-1]]
    data = [history[i][np.isfinite(history[i])] for i in idx]
    labels = ["initial" if i == 0 else f"iter {i}" for i in idx]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), gridspec_kw={"width_ratios": [1, max(len(idx) - 1, 1)]})
    for ax, sel in ((axes[0], [0]), (axes[1], list(range(1, len(idx))) or [0])):
        d = [data[i] if data[i].size else np.array([np.nan]) for i in sel]
        parts = ax.violinplot(d, showmeans=True, showmedians=True)
        parts["cmeans"].set_color("tab:red")
        parts["cmedians"].set_color("tab:green")
        parts["cmedians"].set_linestyle("--")
        ax.set_xticks(range(1, len(sel) + 1), [labels[i] for i in sel])
        ax.set_ylabel("RPE per frame (mm)")
    axes[0].set_title("initial geometry")
    axes[1].set_title(title + skipped, fontsize=10)
    axes[1].legend(
        handles=[
            Line2D([], [], color="tab:red", label="mean"),
            Line2D([], [], color="tab:green", linestyle="--", label="median"),
            Line2D([], [], color="tab:blue", label="extremes"),
        ],
        loc="upper right",
        fontsize=8,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def corrections_plot(
    path: Path, corrections: dict[str, np.ndarray], title: str, truth: dict[str, np.ndarray] | None = None
) -> None:
    """Estimated per-view correction (rotation angles, isocenter shift) against frame index (PNG), with the
    true correction dashed where the scan is simulated."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frame = corrections["frame"]
    rot = np.degrees(corrections["rotvec_rad"])
    shift = corrections["shift_mm"]
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    colors = ("tab:blue", "tab:orange", "tab:green")
    for j, name in enumerate("xyz"):
        a1.plot(frame, rot[:, j], color=colors[j], label=f"rotation about {name}")
        a2.plot(frame, shift[:, j], color=colors[j], label=f"shift {name}")
    if truth is not None:
        for j, name in enumerate("xyz"):
            a1.plot(
                truth["frame"],
                np.degrees(truth["rotvec_rad"][:, j]),
                color=colors[j],
                linestyle="--",
                linewidth=1.0,
                alpha=0.8,
                label=f"true, about {name}",
            )
            a2.plot(
                truth["frame"],
                truth["shift_mm"][:, j],
                color=colors[j],
                linestyle="--",
                linewidth=1.0,
                alpha=0.8,
                label=f"true {name}",
            )
        title += " (dashed: simulation truth in the calibrated frame)"
        fig.text(
            0.01,
            0.005,
            "A shift along a view's beam only changes its magnification; the BBs determine it "
            "weakly, so judge the calibration by its pixel accuracy (table1), not by this component.",
            fontsize=7,
            color="0.3",
        )
    a1.set_ylabel("deg")
    a2.set_ylabel("mm")
    a2.set_xlabel("frame index")
    for ax in (a1, a2):  # beside the axes, never over the data
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, borderaxespad=0.0)
    a1.set_title(title)
    fig.tight_layout(rect=(0.0, 0.02, 1.0, 1.0))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def worst_view_plot(path: Path, result: CalibrationResult) -> None:
    """The view predicted worst (or the middle projection): its line integrals with each BB found there (circle,
    numbered as in the BB table) and where the calibrated geometry puts every BB (cross) (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from orbitct.scanfile import ScanFile

    q = result.quality
    views = np.flatnonzero(np.isfinite(result.geometry.vectors[:, 0]))
    if q is not None and q.worst_frame is not None:
        frame, why = int(q.worst_frame), "the view predicted worst"
    elif views.size:
        frame, why = int(views[views.size // 2]), "the middle view"
    else:
        return
    with ScanFile(result.path) as sf:
        image = sf.line_integrals(frame)
    found = result.uv[frame]
    placed = result.geometry[[frame]].project(result.xyz)[0] if np.isfinite(result.geometry.vectors[frame, 0]) else None
    fig, ax = plt.subplots(figsize=(7, 7 * image.shape[0] / image.shape[1] + 0.4))
    lo, hi = np.percentile(image, [1, 99.5])
    ax.imshow(image, cmap="gray", vmin=lo, vmax=hi, origin="upper")
    ok = np.isfinite(found[:, 0])
    ax.scatter(found[ok, 0], found[ok, 1], s=90, facecolors="none", edgecolors="tab:orange", label="BB found")
    for k in np.flatnonzero(ok):
        ax.annotate(str(k + 1), found[k], xytext=(6, 6), textcoords="offset points", color="tab:orange", fontsize=8)
    if placed is not None:
        ax.scatter(placed[:, 0], placed[:, 1], marker="+", s=60, color="tab:cyan", label="calibrated geometry")
    predicted = float(result.predicted_px[frame]) if result.predicted_px is not None else float("nan")
    code = int(result.view_status[frame]) if result.view_status is not None else -1
    status = {0: "solved from its own BBs", 1: "bridged from its neighbours", 2: "failed"}.get(code, "")
    ax.set_title(
        f"frame {frame}, {why}\n{int(ok.sum())} of {len(found)} BBs found, {status}"
        + (f", predicted error {predicted:.2f} px" if np.isfinite(predicted) else ""),
        fontsize=10,
    )
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, borderaxespad=0.0)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)


def _bb_table(result: CalibrationResult) -> str:
    """The BBs by number (as ``--scale-bar-bbs`` names them), with their positions and how often each was seen."""
    seen = np.isfinite(result.uv[..., 0]).sum(0)
    rows = "\n".join(
        f"| {k + 1} | {x:.2f} | {y:.2f} | {z:.2f} | {int(seen[k])} |" for k, (x, y, z) in enumerate(result.xyz)
    )
    return (
        f"\n## BBs (object frame)\n\n{result.scale_line()}.\n\n| BB | x (mm) | y (mm) | z (mm) | frames |\n"
        "| ---: | ---: | ---: | ---: | ---: |\n" + rows + "\n"
    )


def write_report(
    result: CalibrationResult, out_dir: Path, extra_columns: dict[str, dict[str, Any]] | None = None
) -> list[Path]:
    """Write table1.md, table1.csv, rpe_violin.png, corrections.png and worst_view.png into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    n_last = len(result.iterations) - 1
    if result.method == "paper" and n_last > PAPER_ITERATION:  # the published table's iteration, later ones beside it
        columns = {
            f"this scan (paper, iteration {PAPER_ITERATION})": table1_row(result, PAPER_ITERATION),
            f"this scan (paper, iteration {n_last})": table1_row(result, n_last),
        }
    else:
        columns = {f"this scan ({result.method})": table1_row(result)}
    columns.update(extra_columns or {})
    q = result.quality
    quality = ""
    if q is not None:
        quality = (
            f"\n## Quality: {'passed' if q.passed else 'FAILED'}\n\n- {q.line()}; largest allowed "
            f"{q.threshold_px:g} px\n" + "".join(f"- {r}\n" for r in q.reasons)
        )
    md = out_dir / "table1.md"
    iters = "\n".join(
        f"| {s.index} | {s.rpe_mean_mm:.4f} | {s.rpe_median_mm:.4f} | {s.rpe_std_mm:.4f} | {s.reproj_rms_px:.4f} |"
        for s in result.iterations
    )
    md.write_text(
        f"# Calibration of {result.path.name} ({result.method})\n\n"
        + markdown_table(columns)
        + "\n## RPE per iteration (0 = initial geometry)\n\n| iteration | mean (mm) | median (mm) | std (mm) | reproj. RMS (px) |\n"
        "| ---: | ---: | ---: | ---: | ---: |\n"
        + iters
        + "\n"
        + quality
        + _bb_table(result)
        + ("\n## Warnings\n\n" + "\n".join(f"- {w}" for w in result.warnings) + "\n" if result.warnings else "")
    )
    csv_path = out_dir / "table1.csv"
    write_csv(csv_path, columns)
    violin = out_dir / "rpe_violin.png"
    violin_plot(violin, result.rpe_history, f"{result.method}: after each iteration")
    corr = out_dir / "corrections.png"
    corrections_plot(
        corr, result.corrections, f"{result.method}: estimated correction per view", truth=result.true_corrections
    )
    worst = out_dir / "worst_view.png"
    worst_view_plot(worst, result)
    return [md, csv_path, violin, corr] + ([worst] if worst.exists() else [])
