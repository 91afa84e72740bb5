"""Files a command will write (a recording, a result, a CAT062 capture, a sites file): refused
before any work or connection when they cannot be written, each with one clear line."""

from __future__ import annotations

import os
from pathlib import Path


def check_writable(path: Path, what: str) -> None:
    """Raise ValueError (the command's exit status 2), its message starting with ``what`` (the
    flag, e.g. ``--out``), unless a file can be written at ``path``."""
    if path.is_dir():
        raise ValueError(f"{what} {path} is a directory: give a file name, e.g. {path / 'out'}")
    parent = path.parent
    if not parent.is_dir():
        raise ValueError(f"{what} {path}: the directory {parent} does not exist")
    if path.exists() and not os.access(path, os.W_OK):
        raise ValueError(f"{what} {path}: the file exists and is not writable")
    if not path.exists() and not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"{what} {path}: the directory {parent} is not writable")
