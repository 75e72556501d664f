"""matplotlib for the benchmarks that draw figures: imported at the top of those modules, so a
missing matplotlib stops them before they measure anything, not when the figure is drawn."""
from __future__ import annotations

import matplotlib


def pyplot():
    """matplotlib.pyplot on the file-only Agg backend (no display here); the backend is chosen
    only when a figure is drawn, so that importing a benchmark changes no matplotlib setting."""
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
