"""Writing output files safely: atomically, and never over an existing file unless asked.

Every writer of :mod:`cdra_jax.io` (measurement CSV, result JSON, frame-error files) goes through
:func:`write_text_atomic`: the text is written to a temporary file in the destination folder and
then moved into place in one step, so a reader (or a crash) never sees half a file. Without
``force`` an existing destination is never replaced; the check and the move are one atomic step
where the file system supports hard links (``os.link`` fails when the name exists).
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import uuid
from pathlib import Path
from typing import Any


class OutputExistsError(FileExistsError):
    """The output file exists and ``force`` was not given."""


def _exists_message(path: Path) -> str:
    return f"{path}: file exists; refusing to overwrite it (pass force=True, or --force)"


def write_text_atomic(path: str | os.PathLike, text: str, *, force: bool = False) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path.

    Args:
        path: destination file; its folder must exist.
        text: the whole content.
        force: replace an existing file. Without it an existing file raises
            :class:`OutputExistsError` and is left untouched.

    Raises:
        OutputExistsError: ``path`` exists and ``force`` is false.
        OSError: the folder does not exist or is not writable (message names the path).
    """
    path = Path(path)
    if not force and path.exists():
        raise OutputExistsError(_exists_message(path))
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"{path}: folder {folder} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it 0600; give it a normal file's mode
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        if force:
            os.replace(tmp, path)
        else:
            _move_no_clobber(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return path


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _move_no_clobber(tmp: str, path: Path) -> None:
    """Move ``tmp`` to ``path`` unless ``path`` exists (atomic where hard links work)."""
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise OutputExistsError(_exists_message(path)) from None
    except OSError:
        # No hard links on this file system: check, then replace (a small race remains).
        if path.exists():
            raise OutputExistsError(_exists_message(path)) from None
        os.replace(tmp, path)
        return
    os.unlink(tmp)


def json_text(obj: Any) -> str:
    """JSON text with 2-space indentation, each flat list of numbers on one line.

    Floats are written as ``repr`` (exact round trip); ``NaN``/``inf`` are refused (JSON has
    none; callers write ``null``). A 4x4 matrix reads as four lines of four numbers.
    """
    token = f"@@{uuid.uuid4().hex}@@"
    leaves: list[str] = []

    def mark(o: Any) -> Any:
        if isinstance(o, dict):
            return {k: mark(v) for k, v in o.items()}
        if isinstance(o, list | tuple):
            if o and all(_is_number(v) for v in o):
                leaves.append(json.dumps(list(o), allow_nan=False))
                return f"{token}{len(leaves) - 1}"
            return [mark(v) for v in o]
        return o

    text = json.dumps(mark(obj), indent=2, allow_nan=False)
    for i in reversed(range(len(leaves))):  # reversed: token1 must not eat token10
        text = text.replace(f'"{token}{i}"', leaves[i])
    return text + "\n"


def _is_number(v: Any) -> bool:
    return v is None or (isinstance(v, int | float) and not isinstance(v, bool))
