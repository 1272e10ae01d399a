"""Write the node parameter tables of docs/parameters.md from each node's ``PARAMETERS``
(``equidiff_ros.parameters.with_parameter_tables``).

Usage: python scripts/gen_parameters_doc.py   (from the repository root; run it after changing a node's parameters)
"""

from __future__ import annotations

from pathlib import Path

from equidiff_ros.parameters import node_parameters, with_parameter_tables

if __name__ == "__main__":
    target = Path(__file__).resolve().parents[1] / "docs" / "parameters.md"
    target.write_text(with_parameter_tables(target.read_text(), node_parameters()))
    print(f"wrote {target}")
