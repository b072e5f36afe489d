"""The e-stop test's outputs: the table, the JSON, the plot, the limits, the exit code."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from arena.estop_test.analysis import MEASURES, Breach, Trial, breaches, summarize


def table(results: Mapping[str, Sequence[Trial]]) -> str:
    """p50 / p99 / max of every measure per stop path, and motion after the stop."""
    header = f"{'stop path':<28}" + "".join(f"{m:>24}" for m in MEASURES) + "  moved_after_stop"
    lines = [header, " " * 28 + "".join(f"{'p50 / p99 / max':>24}" for _ in MEASURES)]
    for path, trials in results.items():
        summary = summarize(trials)
        cells = []
        for measure in MEASURES:
            figures = summary.get(measure)
            cells.append(
                f"{'-':>24}"
                if figures is None
                else f"{figures['p50']:>8.1f}{figures['p99']:>8.1f}{figures['max']:>8.1f}"
            )
        moved = sum(t.moved_after_stop for t in trials)
        lines.append(f"{path:<28}" + "".join(cells) + f"  {moved} of {len(trials)}")
    return "\n".join(lines)


def as_json(
    results: Mapping[str, Sequence[Trial]], found: Sequence[Breach], notes: Sequence[str] = ()
) -> dict[str, Any]:
    """Everything: per path its summary, whether anything moved after a stop, each trial; the
    limits broken; and notes on the paths left out, and why."""
    return {
        "notes": list(notes),
        "paths": {
            path: {
                "summary": summarize(trials),
                "moved_after_stop": any(t.moved_after_stop for t in trials),
                "trials": [t.to_json() for t in trials],
            }
            for path, trials in results.items()
        },
        "breaches": [str(b) for b in found],
        "passed": not found,
    }


def check(
    results: Mapping[str, Sequence[Trial]], limits: Mapping[str, Mapping[str, float]]
) -> list[Breach]:
    """Every breach of every path."""
    return [b for path, trials in results.items() for b in breaches(path, trials, limits)]


def plot(results: Mapping[str, Sequence[Trial]], output: Path, window: float = 1.5) -> Path:
    """Position against time around each stop: a panel per path, a line per trial and
    joint that moved, t = 0 at the trigger, the median e-stop marked. Needs matplotlib."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = list(results)
    figure, axes = plt.subplots(
        len(paths), 1, figsize=(8, 2.4 * len(paths)), squeeze=False, sharex=True
    )
    for axis, path in zip(axes[:, 0], paths, strict=True):
        trials = results[path]
        for number, trial in enumerate(trials):
            moved = [j for j, stop in trial.joints.items() if stop.distance_deg > 0]
            for joint in moved or list(trial.joints)[:1]:
                points = [(t, pose[joint]) for t, pose in trial.trace if joint in pose]
                points = [(t, v) for t, v in points if -window <= t <= window]
                if points:
                    times, values = zip(*points, strict=True)
                    axis.plot(times, values, linewidth=1, label=f"{joint} #{number + 1}")
        stops = summarize(trials).get("estopped_ms")
        if stops is not None:
            axis.axvline(stops["p50"] / 1000.0, color="red", linestyle="--", linewidth=1)
        axis.axvline(0.0, color="black", linewidth=0.8)
        axis.set_title(path, fontsize=9, loc="left")
        axis.set_ylabel("degrees")
    axes[-1, 0].set_xlabel("seconds from the trigger (dashed: e-stopped, median)")
    figure.tight_layout()
    figure.savefig(output, dpi=110)
    plt.close(figure)
    return output


def write_json(path: Path, value: Any) -> None:
    """`value` as indented JSON."""
    path.write_text(json.dumps(value, indent=2) + "\n", encoding="utf-8")
