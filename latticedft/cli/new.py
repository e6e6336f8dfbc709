"""latticedft new NAME [--like TEMPLATE]: write a runnable case folder NAME/ from a template.

The folder holds case.toml (every key commented), make_data.py (makes data/ with latticedft.systems),
README.md and data/, written at once by running make_data.py: `latticedft run NAME` works straight away.
An existing folder that is not empty is refused.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import logging
import os
import runpy
import shutil
import tempfile
from pathlib import Path

from .._errors import InputError
from ._common import OK
from ._templates import DEFAULT_TEMPLATE, TEMPLATES, Template

log = logging.getLogger("latticedft")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "new",
        help="write a new case folder from a template (runs at once: latticedft run NAME)",
        description=__doc__,
    )
    p.add_argument("name", metavar="NAME", help="the case folder to create (must not exist, or be empty)")
    p.add_argument(
        "--like",
        choices=list(TEMPLATES),
        default=DEFAULT_TEMPLATE,
        help="the template: "
        + "; ".join(f"{k}: {t.what}" for k, t in TEMPLATES.items())
        + f" (default {DEFAULT_TEMPLATE})",
    )
    g = p.add_mutually_exclusive_group()
    g.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors on stderr")
    g.add_argument("-v", "--verbose", action="store_true", help="debug messages on stderr too")


def _texts(template: Template, name: str, like: str) -> dict[str, str]:
    """File name -> text of the case folder (data/ is made by running make_data.py)."""
    data_lines = template.data.splitlines()
    fmt = {
        "name": name,
        "like": like,
        "what": template.what,
        "data_list": "\n".join(f"  - `{line.split(': ', 1)[0]}`: {line.split(': ', 1)[1]}" for line in data_lines),
        "data_lines": "\n".join(data_lines),
    }
    return {
        "case.toml": template.case_toml.format(**fmt),
        "make_data.py": template.make_data.format(**fmt),
        "README.md": template.readme.format(**fmt),
    }


def write_case(folder: str | os.PathLike[str], like: str = DEFAULT_TEMPLATE) -> Path:
    """Write the case folder ``folder`` from the template ``like`` and run its make_data.py; returns the folder.

    Everything is written into a staging folder beside ``folder`` first and renamed at the end, so an error
    leaves nothing behind. Raises :class:`InputError` when ``folder`` exists and is not an empty folder.
    """
    if like not in TEMPLATES:
        raise InputError.at("like", f"unknown template {like!r} (templates: {', '.join(TEMPLATES)})")
    dest = Path(folder)
    if dest.is_dir() and any(dest.iterdir()):
        raise InputError(f"{dest}/ exists and is not empty; choose a new name (nothing was written)")
    if dest.exists() and not dest.is_dir():
        raise InputError(f"{dest} exists and is not a folder; choose a new name (nothing was written)")
    name = dest.resolve().name
    parent = dest.resolve().parent
    if not parent.is_dir():
        raise InputError(f"{parent}: folder not found (create it first)")
    tmp = Path(tempfile.mkdtemp(prefix=f".{name}.new-", dir=parent))
    try:
        for file, text in _texts(TEMPLATES[like], name, like).items():
            (tmp / file).write_text(text, encoding="utf-8")
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            runpy.run_path(str(tmp / "make_data.py"), run_name="__main__")
        for line in out.getvalue().splitlines():
            log.debug("make_data.py: %s", line)
        if dest.is_dir():
            dest.rmdir()  # empty (checked above)
        tmp.rename(dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return dest


def main(args: argparse.Namespace, argv: list[str]) -> int:
    dest = write_case(args.name, args.like)
    files = sorted(p.name for p in (dest / "data").iterdir())
    print(f"wrote {dest}/ ({args.like}): case.toml, make_data.py, README.md, data/ ({', '.join(files)})")
    print(f"next: latticedft run {dest}")
    return OK
