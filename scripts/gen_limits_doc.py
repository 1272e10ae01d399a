"""Write docs/limits.md from the config declarations (``equidiff_core.limits_table.limits_markdown``).

Usage: python scripts/gen_limits_doc.py   (from the repository root; run it after changing a bounded field)
"""

from __future__ import annotations

from pathlib import Path

from equidiff_core.limits_table import limits_markdown

if __name__ == "__main__":
    target = Path(__file__).resolve().parents[1] / "docs" / "limits.md"
    target.write_text(limits_markdown())
    print(f"wrote {target}")
