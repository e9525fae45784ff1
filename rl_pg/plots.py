"""Figures written as PNG files, without pyplot.

Matplotlib's object API needs no backend: plotting here never switches the backend of
the user's process (a notebook keeps its inline figures) and opens no window.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from rl_pg.checkpoint import write_atomically

if TYPE_CHECKING:
    from matplotlib.axes import Axes

__all__ = ["png_figure"]


@contextmanager
def png_figure(path: str | Path, *, size: tuple[float, float] = (7, 4)) -> Iterator[Axes]:
    """Yields the axes of a new figure; on exit, lays it out and writes it to ``path``
    atomically.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from rl_pg.plots import png_figure
        >>> path = Path(tempfile.mkdtemp()) / "line.png"
        >>> with png_figure(path) as ax:
        ...     _ = ax.plot([0, 1], [0, 1])
        >>> path.read_bytes()[:4]
        b'\\x89PNG'
    """
    # Imported here: a process that never plots (a collector's worker) never loads it.
    from matplotlib.figure import Figure

    figure = Figure(figsize=size)
    yield figure.subplots()
    figure.tight_layout()
    image = io.BytesIO()
    figure.savefig(image, format="png", dpi=100)
    write_atomically(path, image.getvalue())
