"""Writing output files safely: atomically, and never over an existing file unless asked.

Every writer of :mod:`cdra_jax.io` (measurement CSV, result JSON, frame-error files) goes through
:func:`write_text_atomic`: the text is written to a temporary file in the destination folder and
then moved into place in one step, so a reader (or a crash) never sees half a file. Without
``force`` an existing destination is never replaced; the check and the move are one atomic step
where the file system supports hard links (``os.link`` fails when the name exists).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


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
