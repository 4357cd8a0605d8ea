"""Writing a matplotlib figure for the benchmarks and experiments: its folder made, its layout
tightened, the PNG saved, the figure closed (so a script that draws many does not keep them)."""
from __future__ import annotations

from pathlib import Path


def save_figure(fig, path: str | Path, dpi: float | None = None, rect: tuple[float, float, float, float] | None = None) -> Path:
    """Save ``fig`` to ``path`` (parent folders made) at ``dpi`` (default: the figure's), after
    ``tight_layout`` (within ``rect`` when given), and close it. Returns the path."""
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout(**({"rect": rect} if rect is not None else {}))
    fig.savefig(path, dpi=dpi if dpi is not None else "figure")
    plt.close(fig)
    return path
