"""The sigma history of a turntable fit: when each lever arm and proof-mass offset
became observable (docs/turntable.md)."""

from __future__ import annotations

import numpy as np


def sigma_history_plot(res, path, title: str | None = None) -> None:
    """PNG of the 1-sigma of each lever-arm component and proof-mass offset over time
    (the forward filter's covariance), log scale, mm."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(res.tables.get("sigma_history_time", []), float)
    sig = np.asarray(res.tables.get("sigma_history", np.zeros((0, 0))), float)
    labels = list(res.tables.get("sigma_history_labels", []))
    fig, ax = plt.subplots(figsize=(9, 4.8))
    for k, lab in enumerate(labels):
        style = "-" if lab.startswith("lever") else "--"
        ax.semilogy(t - (t[0] if len(t) else 0.0), sig[:, k] * 1e3, style, lw=1.0, label=lab)
    ax.set_xlabel("time from the first cycle's start (s)")
    ax.set_ylabel("1-sigma (mm)")
    ax.set_title(title or "turntable fit: sigma history of lever arms and proof-mass offsets")
    ax.grid(True, which="both", alpha=0.3)
    if labels:
        ax.legend(fontsize=6, ncol=3, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
