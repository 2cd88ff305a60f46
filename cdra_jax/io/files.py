"""Writing output files safely: atomically, and never over an existing file unless asked.

Every file the package writes goes through this module: measurement CSVs, result JSONs,
frame-error and model files (:func:`write_text_atomic`), sweep tables (:func:`write_file_atomic`,
streamed), figures (:func:`save_figure_atomic`: the demo's, ``diagnose --plots``,
``sweep --plot``) and any other bytes (:func:`write_bytes_atomic`). The content is written to a
temporary file in the destination folder, flushed and ``fsync``-ed, then moved into place in one
step, so a reader (or a crash) never sees half a file. Without ``force`` an existing destination
is never replaced; the check and the move are one atomic step where the file system supports
hard links (``os.link`` fails when the name exists), so two writers cannot both "win".

What is never replaced, with or without ``force``: anything that is not a regular file (a folder,
a FIFO, a device node such as ``/dev/null``, a socket). A symbolic link is written through: the
file it points to is replaced (atomically, in the target's folder) and the link stays a link.
The temporary file is removed when the write fails or the process is interrupted (``SIGINT``, and
``SIGTERM`` once :func:`remove_temporary_files_on_sigterm` is installed, as the command line
does).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import stat
import tempfile
import uuid
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import IO, Any


class OutputExistsError(FileExistsError):
    """The output file exists and ``force`` was not given."""


def _exists_message(path: Path) -> str:
    return f"{path}: file exists; refusing to overwrite it (pass force=True, or --force)"


def write_file_atomic(
    path: str | os.PathLike,
    write: Callable[[IO[Any]], object],
    *,
    force: bool = False,
    binary: bool = False,
) -> Path:
    """Write a file atomically by calling ``write(f)`` on an open temporary file; returns the path.

    Args:
        path: destination file; its folder must exist.
        write: fills the open file ``f`` (text, UTF-8 with ``newline=""``, or binary); it may
            write in pieces (bounded memory for large tables).
        force: replace an existing file. Without it an existing file raises
            :class:`OutputExistsError` and is left untouched.
        binary: open the temporary file in binary mode.

    Raises:
        OutputExistsError: ``path`` exists and ``force`` is false.
        OSError: the folder does not exist or is not writable, or ``path`` is not a regular
            file (a folder, FIFO, device or socket; the message names the path and what it is).
    """
    path = destination(path, force)
    folder = path.parent
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    _TEMPORARY.add(tmp)
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it 0600; give it a normal file's mode
        f: IO[Any]
        if binary:
            f = os.fdopen(fd, "wb")
        else:
            f = os.fdopen(fd, "w", encoding="utf-8", newline="")
        with f:
            write(f)
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
    finally:
        _TEMPORARY.discard(tmp)
    return path


_KINDS = (
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def destination(path: str | os.PathLike, force: bool, flag: str | None = None) -> Path:
    """The file an output ``path`` really writes: ``path`` itself, or the target of a symbolic
    link (written through). Raises before any work when the destination exists and is not a
    regular file (whatever ``force`` says), exists without ``force``, or its folder is missing.

    ``flag`` (e.g. ``"--out"``) prefixes messages."""
    where = f"{flag} {path}" if flag else f"{path}"
    p = Path(path)
    if p.is_symlink():
        p = Path(os.path.realpath(p))
    try:
        mode = os.stat(p).st_mode
    except FileNotFoundError:
        mode = None
    if mode is not None:
        if stat.S_ISDIR(mode):
            raise IsADirectoryError(f"{where}: is a folder, expected a file name")
        for test, kind in _KINDS:
            if test(mode):
                raise OutputNotRegularError(
                    f"{where}: is {kind}, not a regular file; refusing to replace it"
                )
        if not force:
            raise OutputExistsError(_exists_message(Path(path)))
    folder = p.parent if str(p.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"{where}: folder {folder} does not exist")
    return p


class OutputNotRegularError(OSError):
    """The output exists and is not a regular file (FIFO, device, socket): never replaced."""


_TEMPORARY: set[str] = set()
"""Temporary files of the writes in progress (removed on ``SIGTERM``)."""


def remove_temporary_files_on_sigterm() -> None:
    """On ``SIGTERM``: remove the temporary files of the writes in progress, say so on stderr
    and end the process at once with exit status 143, whatever it was doing (a compiled
    computation included: no Python code of the interrupted program runs again). Only from the
    main thread; the command line installs it. ``SIGINT`` (Ctrl-C) raises
    ``KeyboardInterrupt`` as usual, whose unwinding removes the temporary file."""

    def _terminate(signum, frame):  # noqa: ARG001
        for tmp in list(_TEMPORARY):
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        with contextlib.suppress(OSError):
            os.write(2, b"error: terminated (SIGTERM); no partial output file was left\n")
        os._exit(128 + signum)

    signal.signal(signal.SIGTERM, _terminate)


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
    return write_file_atomic(path, lambda f: f.write(text), force=force)


def write_bytes_atomic(path: str | os.PathLike, data: bytes, *, force: bool = False) -> Path:
    """Write ``data`` to ``path`` atomically; as :func:`write_text_atomic` otherwise."""
    return write_file_atomic(path, lambda f: f.write(data), force=force, binary=True)


def save_figure_atomic(
    fig: Any, path: str | os.PathLike, *, force: bool = False, **savefig_kwargs: Any
) -> Path:
    """Save a matplotlib figure to ``path`` atomically; returns the path.

    The format comes from the suffix (``.png``, ``.pdf``, ``.svg`` ...; PNG without one), and
    ``savefig_kwargs`` (e.g. ``dpi=120``) go to ``fig.savefig``. Same rules as
    :func:`write_text_atomic`: no overwrite without ``force``, no half-written file.
    """
    path = Path(path)
    fmt = path.suffix[1:].lower() or "png"
    return write_file_atomic(
        path, lambda f: fig.savefig(f, format=fmt, **savefig_kwargs), force=force, binary=True
    )


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


def check_output(path: str | os.PathLike | None, force: bool, flag: str) -> None:
    """Fail before any work when an output cannot be written: it exists (no ``--force``), is not
    a regular file (a folder, FIFO, device or socket: never replaced), or its folder is missing
    (outputs never create folders). See :func:`destination`."""
    if path is not None:
        destination(path, force, flag)


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether paths ``a`` and ``b`` name the same file (``os.path.samefile`` when both exist,
    so links and hard links count; else the resolved paths)."""
    pa, pb = Path(a), Path(b)
    try:
        if pa.exists() and pb.exists():
            return os.path.samefile(pa, pb)
    except OSError:
        pass
    return pa.resolve() == pb.resolve()


def check_distinct_files(
    outputs: Iterable[tuple[str, str | os.PathLike | None]],
    inputs: Iterable[tuple[str, str | os.PathLike | None]] = (),
) -> None:
    """Refuse an output that names the same file as an input or as another output, before any
    work: ``ValueError("--out and --data name the same file")``. Pairs are ``(flag, path)``;
    a ``None`` path is skipped."""
    outs = [(f, p) for f, p in outputs if p is not None]
    ins = [(f, p) for f, p in inputs if p is not None]
    for i, (flag, path) in enumerate(outs):
        for other, q in [*ins, *outs[:i]]:
            if same_file(path, q):
                raise ValueError(f"{flag} and {other} name the same file")
