"""Execute docs/tutorial.ipynb in place, so that the outputs it shows are the ones this version produces.

Usage: ``python docs/make_tutorial.py`` (needs the ``test`` extra: nbclient, nbformat, ipykernel). The test
suite executes the notebook too (``tests/test_tutorial.py``), without writing it.
"""

from __future__ import annotations

from pathlib import Path

import nbformat
from nbclient import NotebookClient

HERE = Path(__file__).resolve().parent


def main() -> None:
    path = HERE / "tutorial.ipynb"
    nb = nbformat.read(path, as_version=4)
    NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(HERE)}}).execute()
    for cell in nb.cells:  # no run-dependent noise in the file: execution counts from 1, no timings
        cell.get("metadata", {}).pop("execution", None)
    nbformat.write(nb, path)
    print(f"executed and wrote {path.name}")


if __name__ == "__main__":
    main()
