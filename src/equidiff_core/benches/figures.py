"""How the benches finish a matplotlib figure: the run's recipe as a note under it, written whole."""

from __future__ import annotations

import textwrap
from pathlib import Path

from ..runtime.output_files import staged_output


def save_with_note(fig, path: Path, note: str = "") -> Path:
    """Lay ``fig`` out with ``note`` wrapped under it (none: the plot alone) and write it to ``path``, replacing
    it whole: a bench's own plot is redrawn on each call of its work folder."""
    if note:
        fig.text(0.5, 0.01, "\n".join(textwrap.wrap(note, 90)), ha="center", va="bottom", fontsize=7)
        fig.tight_layout(rect=(0, 0.07, 1, 1))
    else:
        fig.tight_layout()
    with staged_output(path, force=True) as staged:
        fig.savefig(staged.path)
    return path
