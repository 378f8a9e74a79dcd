"""Headless matplotlib: figures are written to files, never shown."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg", force=False)
import matplotlib.pyplot as plt  # noqa: E402


def new_figure(width: float = 8.0, height: float = 4.0):
    """A (fig, ax) pair with a white background."""
    fig, ax = plt.subplots(figsize=(width, height), constrained_layout=True)
    return fig, ax


def save(fig, path) -> None:
    """Write ``fig`` as PNG at ``path`` (parent folders created) and close it."""
    from pathlib import Path

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=150)
    plt.close(fig)
