"""Error against run time: PSNR (both conditions) and F1@10cm vs wall-clock training time, one curve per variant.

A variant's curve is the list the runner records at its evaluation checkpoints:
    [{"iteration": int, "time_s": float, "psnr_refr": float|None, "psnr_dry": float|None, "f1@0.1": float|None}]
`time_s` is training time only (evaluation pauses the clock), so curves of different variants compare.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt

PANELS = (("psnr_refr", "PSNR refr (dB)"), ("psnr_dry", "PSNR dry (dB)"), ("f1@0.1", "F1 @ 10 cm (%)"))


def error_vs_time(curves: dict[str, list[dict]], path: str | Path, title: str = "") -> Path:
    """Write the three-panel PNG to `path`; points with a None value are left out of that panel."""
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), constrained_layout=True)
    colors = {v: plt.cm.tab10(i % 10) for i, v in enumerate(curves)}  # one colour per variant in every panel
    legend = {}
    for ax, (key, label) in zip(axes, PANELS):
        for variant, curve in curves.items():
            pts = [(c["time_s"] / 60, c[key]) for c in curve if c.get(key) is not None]
            if not pts:
                continue
            x, y = zip(*pts)
            if key == "f1@0.1":
                y = [100 * v for v in y]
            legend[variant] = ax.plot(x, y, marker="o", ms=3, color=colors[variant], label=variant)[0]
        ax.set_xlabel("training wall-clock time (min)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    if legend:
        fig.legend(list(legend.values()), list(legend), loc="outside right center")
    if title:
        fig.suptitle(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
