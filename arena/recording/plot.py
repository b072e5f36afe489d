"""`arena plot`: virtual and real value of each joint over time, e-stops marked (matplotlib)."""

from __future__ import annotations

from pathlib import Path

from arena.extras import require
from arena.recording.analysis import joint_series
from arena.recording.mcap_file import Recording


def plot_recording(recording: Recording, robot_id: str, output: Path) -> Path:
    """Draw one subplot per joint into `output` (PNG, SVG or PDF by suffix)."""
    require("plot", "Plotting").use("Agg")  # no display needed
    import matplotlib.pyplot as plt

    series = joint_series(recording, robot_id)
    joints = series.joints
    figure, axes = plt.subplots(
        len(joints), 1, sharex=True, figsize=(10, 2 * len(joints)), squeeze=False
    )
    for axis, joint in zip(axes[:, 0], joints, strict=True):
        for values, label, style in ((series.virtual, "virtual", "-"), (series.real, "real", "--")):
            points = values.get(joint, [])
            if points:
                axis.plot([p[0] for p in points], [p[1] for p in points], style, label=label)
        for at in series.estops:
            axis.axvline(at, color="red", linewidth=1)
        axis.set_ylabel(f"{joint} (deg)")
        axis.legend(loc="upper right", fontsize="small")
    axes[-1, 0].set_xlabel("seconds" + ("  (red: e-stop)" if series.estops else ""))
    figure.suptitle(f"{recording.path.name}: {robot_id}")
    figure.tight_layout()
    figure.savefig(output)
    plt.close(figure)
    return output
