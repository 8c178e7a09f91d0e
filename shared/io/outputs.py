"""Where a command writes: checked before it starts, so a bad path is one line and exit 2 at once
(a service that dies at its first write under ``restart: unless-stopped`` crash-loops instead)."""

from __future__ import annotations

import os
from pathlib import Path

from fleetmap.shared.errors import BadInput


def output_file(path: str | Path, flag: str) -> Path:
    """A file a command will write: its folder exists and is writable; it is not a folder."""
    p = Path(path)
    if p.is_dir():
        raise BadInput(str(path), f"is a directory ({flag} names a file)")
    folder = p.parent
    if not folder.is_dir():
        raise BadInput(str(path), f"its folder {folder} does not exist ({flag})")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise BadInput(str(path), f"its folder {folder} is not writable ({flag})")
    return p


def output_folder(path: str | Path, flag: str) -> Path:
    """A folder a command will write into, made if needed (with its parents)."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise BadInput(str(path), f"exists and is not a directory ({flag})")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BadInput(str(path), f"cannot be made a folder ({flag}): {exc.strerror}") from None
    if not os.access(p, os.W_OK | os.X_OK):
        raise BadInput(str(path), f"is not writable ({flag})")
    return p
