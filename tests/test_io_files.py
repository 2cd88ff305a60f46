"""Every file the package writes goes through cdra_jax.io.files: atomic, no overwrite without
force, no temporary file left behind, and no race between the existence check and the move."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from matplotlib.figure import Figure

import cdra_jax
from cdra_jax.io import (
    OutputExistsError,
    save_figure_atomic,
    write_bytes_atomic,
    write_file_atomic,
    write_text_atomic,
)


def _figure() -> Figure:
    fig = Figure(figsize=(2, 2))
    fig.add_subplot().plot([0, 1], [1, 0])
    return fig


def test_writers_refuse_to_overwrite_and_leave_no_temporary_file(tmp_path):
    text, data, fig = tmp_path / "a.txt", tmp_path / "b.bin", tmp_path / "c.png"
    assert write_text_atomic(text, "héllo\n") == text
    assert write_bytes_atomic(data, b"\x00\x01") == data
    assert save_figure_atomic(_figure(), fig, dpi=50) == fig
    assert fig.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for path, write in (
        (text, lambda: write_text_atomic(text, "other")),
        (data, lambda: write_bytes_atomic(data, b"other")),
        (fig, lambda: save_figure_atomic(_figure(), fig)),
    ):
        before = path.read_bytes()
        with pytest.raises(OutputExistsError, match=rf"{path.name}: file exists.*force"):
            write()
        assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.bin", "c.png"]
    write_text_atomic(text, "replaced", force=True)
    save_figure_atomic(_figure(), tmp_path / "c.pdf")  # the format follows the suffix
    assert text.read_text() == "replaced" and (tmp_path / "c.pdf").read_bytes()[:4] == b"%PDF"
    with pytest.raises(FileNotFoundError, match="folder .*nope does not exist"):
        write_text_atomic(tmp_path / "nope" / "x.txt", "x")
    with pytest.raises(IsADirectoryError, match="is a folder"):
        write_bytes_atomic(tmp_path, b"x", force=True)


def test_a_file_created_while_writing_is_not_replaced(tmp_path):
    """The existence check and the move are one step: another writer that wins the race keeps
    its file, and ours is refused (its temporary file removed)."""
    path = tmp_path / "r.json"

    def write(f):
        path.write_text("theirs")  # another process creates the file meanwhile
        f.write("ours")

    with pytest.raises(OutputExistsError):
        write_file_atomic(path, write)
    assert path.read_text() == "theirs" and list(tmp_path.iterdir()) == [path]
    write_file_atomic(path, lambda f: f.write("ours"), force=True)
    assert path.read_text() == "ours"


def test_no_module_writes_files_around_the_helpers():
    """Direct writes (savefig to a path, write_text, open for writing, os.replace) appear only
    in cdra_jax/io/files.py."""
    root = Path(cdra_jax.__file__).parent
    pattern = re.compile(
        r"\.savefig\(|\.write_text\(|\.write_bytes\(|os\.replace\(|mkstemp\(|"
        r"open\([^)]*['\"][wax]b?['\"]"
    )
    offenders = [
        f"{path.relative_to(root)}:{i}: {line.strip()}"
        for path in sorted(root.rglob("*.py"))
        if path != root / "io" / "files.py"
        for i, line in enumerate(path.read_text().splitlines(), 1)
        if pattern.search(re.sub(r"``.*?``", "", line)) and not line.lstrip().startswith("#")
    ]
    assert offenders == []
