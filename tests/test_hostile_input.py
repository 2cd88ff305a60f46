"""Hostile input to ``cdra-jax``: every bad file, option and output target gives exit 1 and one
``error: ...`` line naming the place (file, line and column of a CSV; the key of a TOML model;
the option and its range), never a traceback, and leaves every file in the folder as it was.

All through ``cli.main([...])`` in-process (one simulated 12-pose CSV and one model file per
module, so that the calibrations that do run reuse one compiled program), except the signal tests,
which run ``python -m cdra_jax.cli`` in a real process. The catalogue of defects found by QA
comes first (one test each), then the tables and the hypothesis mutations of the CSV and the
model, the option bounds (:data:`cdra_jax.workflows.inputs.BOUNDS`), the output targets,
concurrent writers and the signals.
"""

from __future__ import annotations

import copy
import csv
import hashlib
import json
import math
import os
import queue
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
import types
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np
import pytest
import tomli_w
from _subprocess import checkout_env
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cdra_jax import cli, default_arm, tool_pose
from cdra_jax.io import (
    Measurements,
    OutputExistsError,
    dumps_model,
    load_measurements,
    save_measurements,
    write_text_atomic,
)
from cdra_jax.workflows.inputs import BOUNDS

M = 12  # poses: the shape of every calibration that runs here (one compiled program)
UNRELATED = {"notes.txt": b"not an input\n", ".hidden": b"\x00\x01binary"}


def fuzz(n: int):
    """``n`` examples, no deadline, the same examples on every run: a CI run must not depend on
    chance (an accepted cell value far out of range makes the calibration run to its caps)."""
    return settings(
        max_examples=n,
        deadline=None,
        derandomize=True,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    )


# --------------------------------------------------------------------------- shared files


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """One simulated 12-pose CSV, the default model as a file, and its calibration result."""
    root = tmp_path_factory.mktemp("hostile")
    data, model, ref = root / "data.csv", root / "model.toml", root / "ref.json"
    assert cli.main(["simulate", "--poses", str(M), "--seed", "3", "--out", str(data)]) == 0
    model.write_text(dumps_model(default_arm()))
    argv = ["calibrate", "--model", str(model), "--data", str(data), "--out", str(ref)]
    assert cli.main(argv) == 0
    text = data.read_text()
    lines = text.splitlines(keepends=True)
    h = next(i for i, line in enumerate(lines) if line.startswith("pose,"))
    rows = list(csv.reader(lines[h:]))
    return types.SimpleNamespace(
        root=root,
        text=text,
        model_text=model.read_text(),
        comments="".join(lines[:h]),
        header=rows[0],
        rows=rows[1:],
        H=h + 1,  # 1-based line of the header row; data row k is on line H + k
        frames=_frames(ref),
    )


def _frames(result: Path) -> dict[str, list[float]]:
    r = json.loads(result.read_text())
    return {n: list(f["error_twist"].values()) for n, f in r["frames"].items()}


def _same_frames(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for n in a:
        np.testing.assert_allclose(a[n], b[n], rtol=0, atol=1e-9, err_msg=n)


def _csv_text(comments: str, header, rows, delimiter: str = ",") -> str:
    """CSV text, a cell quoted where it holds the delimiter, a quote or a line break."""

    def cell(v: str) -> str:
        if any(c in v for c in (delimiter, '"', "\r", "\n")):
            return '"' + v.replace('"', '""') + '"'
        return v

    return comments + "".join(delimiter.join(map(cell, r)) + "\n" for r in [header, *rows])


def _folder(base) -> Path:
    """A new empty folder with the unrelated files (hypothesis examples share no folder)."""
    d = Path(tempfile.mkdtemp(dir=base.root))
    for name, content in UNRELATED.items():
        (d / name).write_bytes(content)
    return d


def _snapshot(folder: Path) -> dict[str, tuple]:
    """Every entry under ``folder``: a file by its SHA-256, a link by its target, else its type."""
    out: dict[str, tuple] = {}
    for p in sorted(folder.rglob("*")):
        mode = p.lstat().st_mode
        key = str(p.relative_to(folder))
        if stat.S_ISLNK(mode):
            out[key] = ("link", os.readlink(p))
        elif stat.S_ISREG(mode):
            out[key] = ("file", hashlib.sha256(p.read_bytes()).hexdigest())
        else:
            out[key] = ("other", stat.S_IFMT(mode))
    return out


def _temporaries(folder: Path) -> list[str]:
    return [p.name for p in folder.rglob(".*.tmp")]


def _run(folder: Path, argv, capsys, outputs=()) -> tuple[int, str]:
    """Run ``cdra-jax argv``; returns ``(exit code, stderr)``. Checks: no traceback, no
    temporary file left, no file of ``folder`` changed except the named ``outputs``; on exit 1
    exactly one ``error: ...`` line and nothing created."""
    before = _snapshot(folder)
    rc = cli.main([str(a) for a in argv])
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err + cap.out, cap.err
    after = _snapshot(folder)
    assert not _temporaries(folder), after
    if rc == cli.EXIT_ERROR:
        err = [line for line in cap.err.splitlines() if line.strip()]
        assert len(err) == 1 and err[0].startswith("error: "), cap.err
        assert after == before, "a failed run changed the folder"
        return rc, err[0]
    errors = [ln for ln in cap.err.splitlines() if ln.startswith("error")]
    if rc == cli.EXIT_UNTRUSTED:  # the result is written, marked untrusted
        assert len(errors) == 1 and errors[0].startswith("error: untrusted result: "), cap.err
    else:
        assert not errors, cap.err
    names = {str(Path(o).relative_to(folder)) for o in outputs}
    assert {k: v for k, v in before.items() if k not in names} == {
        k: v for k, v in after.items() if k not in names
    }, "a successful run changed a file it does not write"
    return rc, cap.err


def _calibrate(d: Path, data: Path, model: Path, out: Path | None = None, *extra) -> list:
    return [
        "calibrate",
        "--model",
        model,
        "--data",
        data,
        "--out",
        out or d / "r.json",
        *extra,
    ]


def _inputs(base, d: Path, data: str | bytes | None = None, model: str | bytes | None = None):
    """Write the (mutated) data CSV and model into ``d``; returns their paths."""
    paths = []
    for name, content, default in (
        ("data.csv", data, base.text),
        ("model.toml", model, base.model_text),
    ):
        p = d / name
        content = default if content is None else content
        if isinstance(content, str):
            p.write_bytes(content.encode("utf-8"))
        else:
            p.write_bytes(content)
        paths.append(p)
    return paths


# --------------------------------------------------------------------------- the catalogue


def test_force_onto_a_fifo_is_refused_and_the_fifo_stays(base, capsys):
    d = _folder(base)
    data, model = _inputs(base, d)
    fifo = d / "out.json"
    os.mkfifo(fifo)
    rc, line = _run(d, _calibrate(d, data, model, fifo, "--force"), capsys)
    assert rc == cli.EXIT_ERROR
    assert f"--out {fifo}: is a FIFO (named pipe), not a regular file" in line, line
    assert stat.S_ISFIFO(fifo.lstat().st_mode)


def test_force_onto_a_folder_is_refused(base, capsys):
    d = _folder(base)
    data, model = _inputs(base, d)
    folder = d / "out.json"
    folder.mkdir()
    (folder / "inside.txt").write_text("keep")
    rc, line = _run(d, _calibrate(d, data, model, folder, "--force"), capsys)
    assert rc == cli.EXIT_ERROR
    assert f"--out {folder}: is a folder, expected a file name" in line, line
    assert folder.is_dir() and (folder / "inside.txt").read_text() == "keep"


def test_force_onto_dev_null_is_refused_and_it_stays_a_device(base, capsys):
    devnull = Path("/dev/null")
    assert stat.S_ISCHR(devnull.stat().st_mode)
    d = _folder(base)
    data, model = _inputs(base, d)
    rc, line = _run(d, _calibrate(d, data, model, devnull, "--force"), capsys)
    assert rc == cli.EXIT_ERROR
    assert "--out /dev/null: is a character device, not a regular file" in line, line
    assert stat.S_ISCHR(devnull.stat().st_mode)
    assert not [p for p in Path("/dev").glob(".null.*.tmp")]


def test_out_symlink_is_written_through(base, capsys):
    d = _folder(base)
    data, model = _inputs(base, d)
    target = d / "target.json"
    target.write_text("old")
    link = d / "link.json"
    link.symlink_to(target)
    rc, _ = _run(d, _calibrate(d, data, model, link, "--force"), capsys, outputs=[target])
    assert rc == 0
    assert link.is_symlink() and os.readlink(link) == str(target)
    _same_frames(_frames(target), base.frames)


@pytest.mark.parametrize("value", ["2147483648", "9223372036854775808"])
def test_max_iterations_beyond_the_machine_integers_is_refused(base, capsys, value):
    d = _folder(base)
    data, model = _inputs(base, d)
    rc, line = _run(d, _calibrate(d, data, model, None, "--max-iterations", value), capsys)
    assert rc == cli.EXIT_ERROR
    assert f"--max-iterations must be an integer in [1, 10000], got {value}" in line, line


def test_a_noise_std_of_1e_300_is_refused(base, capsys):
    d = _folder(base)
    data, model = _inputs(base, d)
    argv = _calibrate(d, data, model, None, "--noise-pos", "1e-300", "--noise-rot", "1e-300")
    rc, line = _run(d, argv, capsys)
    assert rc == cli.EXIT_ERROR
    assert "--noise-pos must be a number in [1e-09, 1e+06], got 1e-300" in line, line


def _cell(base, row: int, column: str, value: str) -> str:
    rows = copy.deepcopy(base.rows)
    rows[row - 1][base.header.index(column)] = value
    return _csv_text(base.comments, base.header, rows)


@pytest.mark.parametrize(
    ("column", "value"),
    [("measured.x", "1e308"), ("elbow.q", "1e300")],
    ids=["measured.x = 1e308", "joint value 1e300"],
)
def test_a_huge_number_names_file_line_and_column(base, capsys, column, value):
    d = _folder(base)
    data, model = _inputs(base, d, data=_cell(base, 5, column, value))
    rc, line = _run(d, _calibrate(d, data, model), capsys)
    assert rc == cli.EXIT_ERROR
    assert f"{data}, line {base.H + 5}, column '{column}': '{value}' is beyond 1e+07" in line


def test_a_huge_model_offset_names_the_key(base, capsys):
    d = _folder(base)
    spec = tomllib.loads(base.model_text)
    spec["frames"][0]["xyz"] = [0, 0, 1e300]
    data, model = _inputs(base, d, model=tomli_w.dumps(spec))
    rc, line = _run(d, _calibrate(d, data, model), capsys)
    assert rc == cli.EXIT_ERROR
    assert f"{model}: frames[0] (base).xyz: " in line and "beyond 1e+07 (mm)" in line, line


def test_one_distinct_configuration_is_refused(base, capsys):
    rows = [[f"q{k:02d}", *base.rows[0][1:]] for k in range(M)]
    d = _folder(base)
    data, model = _inputs(base, d, data=_csv_text(base.comments, base.header, rows))
    rc, line = _run(d, _calibrate(d, data, model), capsys)
    assert rc == cli.EXIT_ERROR
    assert f"{data}: {M} rows but only 1 distinct module configuration" in line, line


def test_a_nul_byte_in_a_pose_id_names_line_and_column(base, capsys):
    d = _folder(base)
    data, model = _inputs(base, d, data=_cell(base, 4, "pose", "p\x0004"))
    rc, line = _run(d, _calibrate(d, data, model), capsys)
    assert rc == cli.EXIT_ERROR
    assert f"{data}, line {base.H + 4}, column 'pose': " in line, line
    assert "contains a control character" in line


@pytest.mark.parametrize(
    ("key", "value", "unit"), [("stiffness", 0, "N/mm"), ("mass", -1, "kg")], ids=str
)
def test_a_non_positive_physical_parameter_names_the_key(base, capsys, key, value, unit):
    spec = tomllib.loads(base.model_text)
    spec["modules"][1][key] = value
    d = _folder(base)
    data, model = _inputs(base, d, model=tomli_w.dumps(spec))
    rc, line = _run(d, _calibrate(d, data, model), capsys)
    assert rc == cli.EXIT_ERROR
    assert f"{model}: modules[1] (elbow).{key}: expected a positive number of {unit}" in line


def test_a_byte_order_mark_in_the_model_is_accepted(base, capsys):
    d = _folder(base)
    data, model = _inputs(base, d, model=b"\xef\xbb\xbf" + base.model_text.encode())
    rc, _ = _run(d, _calibrate(d, data, model), capsys, outputs=[d / "r.json"])
    assert rc == 0
    _same_frames(_frames(d / "r.json"), base.frames)


def test_quaternion_files_round_trip_with_x64_off(base):
    arm = default_arm()
    rng = np.random.default_rng(7)
    q = rng.uniform(-0.9, 0.9, (M, arm.dof))
    T = np.asarray(tool_pose(arm, q), dtype=np.float64)
    path = _folder(base) / "quaternions.csv"
    with jax.enable_x64(False):
        save_measurements(Measurements.from_arrays(arm, q, T, orientation="quaternion"), path)
        back = load_measurements(path, arm)
    assert "measured.qw" in path.read_text().splitlines()[0]
    assert back.measured.dtype == np.float64
    np.testing.assert_array_equal(back.q, q)
    assert np.max(np.abs(back.measured - T)) <= 1e-15


# --------------------------------------------------------------------------- CSV table


def _rows(base):
    return copy.deepcopy(base.rows)


def _edit_rows(base, edit: Callable[[list], object], comments: str | None = None) -> str:
    rows = _rows(base)
    header = list(base.header)
    edit(types.SimpleNamespace(rows=rows, header=header))
    return _csv_text(base.comments if comments is None else comments, header, rows)


def _swap_row(c, k: int, j: int, new_id: str) -> None:
    c.rows[k - 1] = [new_id, *c.rows[j - 1][1:]]


def _lines(base) -> list[str]:
    return base.text.splitlines(keepends=True)


def _header_replaced_by_a_row(base) -> str:
    lines = _lines(base)
    del lines[base.H - 1]
    return "".join(lines)


def _truncated(base) -> str:
    text = base.text.rstrip("\n")
    return text[: text.rindex(",") - 5]


def _quoted_newline(base) -> str:
    rows = _rows(base)
    rows[2][base.header.index("wrist.ry")] = "0.1\n0.2"
    return _csv_text(base.comments, base.header, rows)


def _unclosed_quote(base) -> str:
    lines = _lines(base)
    lines[base.H + 3] = '"' + lines[base.H + 3]
    return "".join(lines)


def _comment_after_header(base) -> str:
    lines = _lines(base)
    lines.insert(base.H + 2, "# a late comment\n")
    return "".join(lines)


def _long_cell(base) -> str:
    return _cell(base, 6, "measured.y", "1" * 200_000)


def _cells(column: str, values: list[str]) -> list[tuple[str, str]]:
    return [(column, v) for v in values]


# Cells that are not numbers: (column, cell) -> "line H+3, column ..., not a number/empty".
BAD_NUMBERS = [
    *_cells(
        "measured.rz",
        ["0x1A", "1_000", "1e", "--1", "1.2.3", "+-1", "true", "None", "1,5", "0.5\x00"],
    ),
    *_cells("elbow.q", ["\uff11\uff12", "\u0663", "1.5 mm", "\u22121", "1e5e5", "0b10"]),
]
EMPTY_CELLS = [("shoulder.ry", ""), ("wrist.rz", "   "), ("measured.z", "\t")]
NOT_FINITE = _cells("measured.x", ["1e400", "-1e400", "-inf", "Infinity", "nan", "NAN", "+inf"])
TOO_LARGE = [
    ("measured.z", "1.0000001e7"),
    ("shoulder.rx", "-1e308"),
    ("measured.rx", "1e300"),
    ("wrist.ry", "12345678901234567890"),
]
BAD_IDS = [
    ("", "empty pose identifier"),
    ("  ", "empty pose identifier"),
    ("p\t03", "contains a control character"),
    ("p\x7f03", "contains a control character"),
    ("\x1b[31mred", "contains a control character"),
    ("p\n03", "contains a control character"),
    ("p\r03", "contains a control character"),
]


@pytest.mark.parametrize(("column", "value"), BAD_NUMBERS, ids=repr)
def test_text_in_a_number_cell_names_file_line_and_column(base, capsys, column, value):
    d = _folder(base)
    data, model = _inputs(base, d, data=_cell(base, 3, column, value))
    rc, line = _run(d, _calibrate(d, data, model), capsys)
    assert rc == cli.EXIT_ERROR
    assert f"{data}, line {base.H + 3}, column '{column}': not a number: " in line, line


@pytest.mark.parametrize(("column", "value"), EMPTY_CELLS, ids=repr)
def test_an_empty_cell_names_file_line_and_column(base, capsys, column, value):
    d = _folder(base)
    data, model = _inputs(base, d, data=_cell(base, 7, column, value))
    rc, line = _run(d, _calibrate(d, data, model), capsys)
    assert rc == cli.EXIT_ERROR
    assert line.startswith(f"error: {data}, line {base.H + 7}, column '{column}': empty cell"), line


@pytest.mark.parametrize(("column", "value"), NOT_FINITE + TOO_LARGE, ids=repr)
def test_a_non_finite_or_huge_number_names_file_line_and_column(base, capsys, column, value):
    d = _folder(base)
    data, model = _inputs(base, d, data=_cell(base, 11, column, value))
    rc, line = _run(d, _calibrate(d, data, model), capsys)
    assert rc == cli.EXIT_ERROR
    assert f"{data}, line {base.H + 11}, column '{column}': '{value}' is " in line, line
    assert ("not a finite number" if (column, value) in NOT_FINITE else "beyond 1e+07") in line


@pytest.mark.parametrize(("value", "message"), BAD_IDS, ids=repr)
def test_a_bad_pose_id_names_line_and_column(base, capsys, value, message):
    d = _folder(base)
    data, model = _inputs(base, d, data=_cell(base, 8, "pose", value))
    rc, line = _run(d, _calibrate(d, data, model), capsys)
    assert rc == cli.EXIT_ERROR
    assert f"{data}, line {base.H + 8}, column 'pose': " in line and message in line, line


# name -> (CSV text or bytes of base, expected parts of the error line; {data}, {H} and the
# lines {r1}..{r12} of the data rows are filled in)
BAD_FILES: dict[str, tuple[Callable, list[str]]] = {
    "empty file": (lambda b: "", ["{data}: missing header row"]),
    "comments only": (lambda b: b.comments, ["{data}: missing header row"]),
    "header only": (
        lambda b: b.comments + ",".join(b.header) + "\n",
        ["{data}: 0 measured pose(s); the calibration needs at least 4"],
    ),
    "header replaced by a data row": (
        _header_replaced_by_a_row,
        ["{data}, line {H}: missing header row"],
    ),
    "truncated in the last row": (
        _truncated,
        ["{data}, line {r12}, column 'measured.rz': expected 14 fields", "got 13"],
    ),
    "truncated to 3 rows": (
        lambda b: "".join(_lines(b)[: b.H + 3]),
        ["{data}: 3 measured pose(s); the calibration needs at least 4"],
    ),
    "trailing comma in a row": (
        lambda b: _edit_rows(b, lambda c: c.rows[4].append("")),
        ["{data}, line {r5}: expected 14 fields (one per header column), got 15"],
    ),
    "a missing field": (
        lambda b: _edit_rows(b, lambda c: c.rows[3].pop()),
        ["{data}, line {r4}, column 'measured.rz': expected 14 fields", "got 13"],
    ),
    "duplicated column": (
        lambda b: _edit_rows(
            b, lambda c: [c.header.append("elbow.q")] + [r.append(r[4]) for r in c.rows]
        ),
        ["{data}, line {H} (header row), column 'elbow.q': column appears twice"],
    ),
    "duplicated row": (
        lambda b: _edit_rows(b, lambda c: c.rows.insert(6, list(c.rows[1]))),
        ["{data}, line {r7}, column 'pose': duplicate pose identifier 'p02'", "line {r2}"],
    ),
    "duplicated pose id": (
        lambda b: _edit_rows(b, lambda c: c.rows[10].__setitem__(0, "p11".replace("11", "04"))),
        ["{data}, line {r11}, column 'pose': duplicate pose identifier 'p04'", "line {r4}"],
    ),
    "unquoted # pose id": (
        lambda b: _cell(b, 5, "pose", "#p05"),
        ["{data}, line {r5}: comment line after the header"],
    ),
    "comment after the header": (
        _comment_after_header,
        ["{data}, line {r3}: comment line after the header"],
    ),
    "quoted newline in a number": (
        _quoted_newline,
        ["{data}, line {r3}, column 'wrist.ry': not a number: '0.1\\n0.2'"],
    ),
    "unclosed quote": (_unclosed_quote, ["{data}, line {r4}", "expected 14 fields"]),
    "semicolon delimiter": (
        lambda b: _csv_text(b.comments, b.header, b.rows, ";"),
        ["{data}, line {H}: columns must be separated by commas; this header row uses ';'"],
    ),
    "tab delimiter": (
        lambda b: _csv_text(b.comments, b.header, b.rows, "\t"),
        ["{data}, line {H}: columns must be separated by commas; this header row uses tabs"],
    ),
    "pipe delimiter": (
        lambda b: _csv_text(b.comments, b.header, b.rows, "|"),
        ["{data}, line {H} (header row)"],
    ),
    "upper-case header": (
        lambda b: b.text.replace(",".join(b.header), ",".join(b.header).upper()),
        ["{data}, line {H} (header row), column 'pose': missing column 'pose'"],
    ),
    "unknown column": (
        lambda b: _edit_rows(
            b, lambda c: [c.header.append("humidity ")] + [r.append("0.4") for r in c.rows]
        ),
        ["{data}, line {H} (header row), column 'humidity': unknown column"],
    ),
    "orientation columns of both kinds": (
        lambda b: _edit_rows(
            b, lambda c: [c.header.append("measured.qw")] + [r.append("1") for r in c.rows]
        ),
        ["{data}, line {H} (header row)", "measured.qw"],
    ),
    "UTF-16": (lambda b: b.text.encode("utf-16"), ["{data}: not UTF-8 text"]),
    "UTF-16-LE without BOM": (  # ASCII as UTF-16-LE is valid UTF-8 with NULs in between
        lambda b: b.text.encode("utf-16-le"),
        ["{data}, line 2 (header row), column 'pose': missing column 'pose'"],
    ),
    "UTF-32": (lambda b: b.text.encode("utf-32"), ["{data}: not UTF-8 text"]),
    "Latin-1 pose id": (
        lambda b: _cell(b, 2, "pose", "pos\xe9").encode("latin-1"),
        ["{data}: not UTF-8 text"],
    ),
    "random bytes": (lambda b: bytes(range(128, 256)) * 20, ["{data}: not UTF-8 text"]),
    "a rotation vector beyond 1000 rad": (
        lambda b: _cell(b, 9, "measured.ry", "2000"),
        ["{data}, line {r9}, column 'measured.ry': rotation vector", "above the limit 1000"],
    ),
}


@pytest.mark.parametrize(
    "case",
    [
        *BAD_FILES,
        "a 200000-character cell",
    ],
)
def test_malformed_csv_files_give_one_error_line(base, capsys, case):
    edit, parts = (
        BAD_FILES[case]
        if case in BAD_FILES
        else (_long_cell, ["{data}, line {r6}: malformed CSV record"])
    )
    d = _folder(base)
    data, model = _inputs(base, d, data=edit(base))
    rc, line = _run(d, _calibrate(d, data, model), capsys)
    assert rc == cli.EXIT_ERROR, line
    subs = {"data": data, "H": base.H, **{f"r{k}": base.H + k for k in range(1, M + 1)}}
    for part in parts:
        assert part.format(**subs) in line, (case, line)


def _aux(base, name: str, value: str) -> str:
    return _edit_rows(base, lambda c: [c.header.append(name)] + [r.append(value) for r in c.rows])


def _row_over_another(c) -> None:
    _swap_row(c, 12, 5, "p05-again")


# Files that are accepted: name -> (CSV text or bytes of base, same calibration as the original)
ACCEPTED = {
    "UTF-8 byte-order mark": (lambda b: b"\xef\xbb\xbf" + b.text.encode(), True),
    "CRLF line ends": (lambda b: b.text.replace("\n", "\r\n"), True),
    "CR line ends": (lambda b: b.text.replace("\n", "\r"), True),
    "blank lines between rows": (lambda b: b.text.replace("\np0", "\n\n  \np0"), True),
    "spaces around cells": (
        lambda b: _edit_rows(b, lambda c: [r.__setitem__(3, f"  {r[3]}\t") for r in c.rows]),
        True,
    ),
    "every cell quoted": (
        lambda b: (
            b.comments + "".join(",".join(f'"{v}"' for v in r) + "\n" for r in [b.header, *b.rows])
        ),
        True,
    ),
    "no comments": (lambda b: b.text[len(b.comments) :], True),
    "unicode and long pose ids": (
        lambda b: _edit_rows(
            b,
            lambda c: [
                c.rows[0].__setitem__(0, "pöse-\u4e00"),
                c.rows[1].__setitem__(0, "x" * 5000),
            ],
        ),
        True,
    ),
    "quoted # pose id": (lambda b: b.text.replace("\np05,", '\n"#p05",'), True),
    "a row copied over another (new id)": (lambda b: _edit_rows(b, _row_over_another), False),
    "an auxiliary column of 1e-300": (lambda b: _aux(b, "temperature_c", "1e-300"), True),
    "an auxiliary column that underflows (1e-400)": (
        lambda b: _aux(b, "payload_kg", "1e-400"),
        True,
    ),
    "a negative zero": (lambda b: _cell(b, 2, "shoulder.rx", "-0.0"), False),
}


@pytest.mark.parametrize("case", list(ACCEPTED))
def test_harmless_variations_are_accepted(base, capsys, case):
    edit, same = ACCEPTED[case]
    d = _folder(base)
    data, model = _inputs(base, d, data=edit(base))
    out = d / "r.json"
    rc, err = _run(d, _calibrate(d, data, model, out), capsys, outputs=[out])
    assert rc == 0, err
    assert json.loads(out.read_text())["converged"] is True
    if same:
        _same_frames(_frames(out), base.frames)


# --------------------------------------------------------------------------- model table


def _spec_edit(path: tuple, value):
    def edit(spec):
        node = spec
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value

    return edit


# name -> (edit of the parsed model (dict) or of its text (str -> str | bytes), expected parts)
BAD_MODELS: dict[str, tuple[Callable, list[str]]] = {
    "xyz beyond 1e7": (
        _spec_edit(("frames", 1, "xyz"), [1e8, 0.0, 0.0]),
        ["{model}: frames[1] (upper_arm).xyz: ", "beyond 1e+07 (mm)"],
    ),
    "xyz NaN": (
        _spec_edit(("frames", 2, "xyz"), [0.0, math.nan, 250.0]),
        ["{model}: frames[2] (forearm).xyz: contains a non-finite number"],
    ),
    "xyz inf": (
        _spec_edit(("frames", 3, "xyz"), [math.inf, 0.0, 80.0]),
        ["{model}: frames[3] (tool).xyz: contains a non-finite number"],
    ),
    "xyz with two numbers": (
        _spec_edit(("frames", 0, "xyz"), [0.0, 0.0]),
        ["{model}: frames[0] (base).xyz: expected a list of 3 numbers"],
    ),
    "xyz as text": (
        _spec_edit(("frames", 0, "xyz"), ["0", "0", "50"]),
        ["{model}: frames[0] (base).xyz: expected a list of 3 numbers"],
    ),
    "xyz a 400-digit integer": (
        _spec_edit(("frames", 0, "xyz"), [0, 0, 10**400]),
        ["{model}: frames[0] (base).xyz: "],
    ),
    "rotvec 1e300": (
        _spec_edit(("frames", 1, "rotvec"), [1e300, 0.0, 0.0]),
        ["{model}: frames[1] (upper_arm).rotvec: "],
    ),
    "rotvec 2000 rad": (
        _spec_edit(("frames", 1, "rotvec"), [2000.0, 0.0, 0.0]),
        ["{model}: frames[1] (upper_arm).rotvec: angle 2000 rad is above 1000 rad"],
    ),
    "pretension 0": (
        _spec_edit(("modules", 0, "pretension"), 0),
        ["{model}: modules[0] (shoulder).pretension: expected a positive number of N"],
    ),
    "pretension NaN": (
        _spec_edit(("modules", 0, "pretension"), math.nan),
        ["{model}: modules[0] (shoulder).pretension: ", "got nan"],
    ),
    "pretension above 1e9": (
        _spec_edit(("modules", 2, "pretension"), 2e9),
        ["{model}: modules[2] (wrist).pretension: ", "up to 1e+09"],
    ),
    "mass inf": (
        _spec_edit(("modules", 2, "mass"), math.inf),
        ["{model}: modules[2] (wrist).mass: ", "got inf"],
    ),
    "mass as text": (
        _spec_edit(("modules", 0, "mass"), "0.4"),
        ["{model}: modules[0] (shoulder).mass: ", "got '0.4'"],
    ),
    "mass true": (
        _spec_edit(("modules", 0, "mass"), True),
        ["{model}: modules[0] (shoulder).mass: ", "got True"],
    ),
    "stiffness negative": (
        _spec_edit(("modules", 2, "stiffness"), -33.0),
        ["{model}: modules[2] (wrist).stiffness: expected a positive number of N/mm"],
    ),
    "limits reversed": (
        _spec_edit(("modules", 1, "limits"), [[2.0, 0.0]]),
        ["{model}: modules[1] (elbow).limits: expected 1 pairs [low, high] with low < high"],
    ),
    "limits 1e300": (
        _spec_edit(("modules", 1, "limits"), [[-1e300, 1e300]]),
        ["{model}: modules[1] (elbow).limits: ", "beyond 1000 rad"],
    ),
    "limits NaN": (
        _spec_edit(("modules", 0, "limits"), [[-1.0, 1.0], [math.nan, 1.0], [-1.0, 1.0]]),
        ["{model}: modules[0] (shoulder).limits: expected 3 pairs"],
    ),
    "axis zero": (
        _spec_edit(("modules", 1, "axis"), [0.0, 0.0, 0.0]),
        ["{model}: modules[1] (elbow): 'axis' must be non-zero"],
    ),
    "unknown kind": (
        _spec_edit(("modules", 1, "kind"), "telescopic"),
        ["{model}: modules[1] (elbow): 'kind' must be one of"],
    ),
    "cable base NaN": (
        _spec_edit(("modules", 0, "cables", 2, "base"), [math.nan, 0.0, 0.0]),
        ["{model}: modules[0] (shoulder).cables[2].base: contains a non-finite number"],
    ),
    "cable platform beyond 1e7": (
        _spec_edit(("modules", 2, "cables", 0, "platform"), [0.0, 0.0, -2e7]),
        ["{model}: modules[2] (wrist).cables[0].platform: ", "beyond 1e+07"],
    ),
    "com inf": (
        _spec_edit(("modules", 1, "com"), [0.0, 0.0, -math.inf]),
        ["{model}: modules[1] (elbow).com: contains a non-finite number"],
    ),
    "gravity NaN": (
        _spec_edit(("gravity",), [0.0, 0.0, math.nan]),
        ["{model}: gravity: contains a non-finite number"],
    ),
    "a frame missing": (
        lambda s: s["frames"].pop(),
        ["{model}: top level: 3 modules need 4 [[frames]]", "got 3"],
    ),
    "a module name with a dot": (
        _spec_edit(("modules", 1, "name"), "el.bow"),
        ["{model}: modules[1] (el.bow): a module name makes the measurement file's column"],
    ),
    "a reserved module name": (
        _spec_edit(("modules", 1, "name"), "pose"),
        ["{model}: modules[1] (pose): 'pose' is reserved"],
    ),
    "a repeated name": (
        _spec_edit(("modules", 1, "name"), "wrist"),
        ["{model}: top level: frame and module names must be unique, repeated: ['wrist']"],
    ),
    "empty": (lambda s: s.clear(), ["{model}: top level: needs a 'name' (string)"]),
}

# name -> (edit of the model text (str -> str | bytes), expected parts of the error line)
BAD_MODEL_TEXTS: dict[str, tuple[Callable, list[str]]] = {
    "not TOML": (lambda t: t.replace("[[modules]]", "[[modules]", 1), ["{model}: not valid TOML"]),
    "truncated": (lambda t: t[: len(t) // 2] + "xyz = [", ["{model}: not valid TOML"]),
    "a key given twice": (
        lambda t: t.replace('name = "cdra"', 'name = "cdra"\nname = "again"', 1),
        ["{model}: not valid TOML"],
    ),
    "binary junk": (lambda t: "\x00\x01\x02 = 1\n", ["{model}: not valid TOML"]),
}

BAD_MODEL_ENCODINGS = {
    "UTF-16": lambda t: t.encode("utf-16"),
    "Latin-1 description": lambda t: t.replace("7-DOF", "7-DOF \xe0 c\xe2bles").encode("latin-1"),
}
DEEP = "[" * 100_000 + "]" * 100_000


def _model_case(base, case: str) -> tuple[str | bytes, list[str]]:
    """The model file content of ``case`` and the expected parts of the error line."""
    if case in BAD_MODELS:
        edit, parts = BAD_MODELS[case]
        spec = tomllib.loads(base.model_text)
        edit(spec)
        return tomli_w.dumps(spec), parts
    if case in BAD_MODEL_TEXTS:
        edit, parts = BAD_MODEL_TEXTS[case]
        return edit(base.model_text), parts
    if case in BAD_MODEL_ENCODINGS:
        return BAD_MODEL_ENCODINGS[case](base.model_text), ["{model}: ", "UTF-8"]
    return base.model_text.replace("[[frames]]", f"deep = {DEEP}\n\n[[frames]]", 1), ["{model}: "]


@pytest.mark.parametrize(
    "case",
    [
        *BAD_MODELS,
        *BAD_MODEL_TEXTS,
        *BAD_MODEL_ENCODINGS,
        "arrays nested 100000 deep",
    ],
)
def test_malformed_model_files_name_the_key(base, capsys, case):
    content, parts = _model_case(base, case)
    d = _folder(base)
    data, model = _inputs(base, d, model=content)
    rc, line = _run(d, _calibrate(d, data, model), capsys)
    assert rc == cli.EXIT_ERROR, line
    for part in parts:
        assert part.format(model=model) in line, (case, line)


# --------------------------------------------------------------------------- hypothesis

CELL_TEXT = st.one_of(
    st.text(max_size=12),
    st.text(alphabet="0123456789+-.eE_ nafiINFx,\"'#\t\r\n\x00", max_size=10),
    st.floats().map(repr),
    st.floats(width=32).map(lambda v: f"{v:.3g}"),
    st.integers().map(str),
    st.sampled_from(["", " ", "nan", "-inf", "1e308", "1e-320", "1e7", "-1e7", "10000001", "٣"]),
)
NUMERIC = [
    "shoulder.rx",
    "shoulder.ry",
    "shoulder.rz",
    "elbow.q",
    "wrist.rx",
    "wrist.ry",
    "wrist.rz",
    "measured.x",
    "measured.y",
    "measured.z",
    "measured.rx",
    "measured.ry",
    "measured.rz",
]


@fuzz(25)
@given(row=st.integers(1, M), column=st.sampled_from(NUMERIC), value=CELL_TEXT)
def test_random_cell_values_are_read_or_named(base, capsys, row, column, value):
    """Any text in a number cell: exit 0/3 (a number the readers accept) or exit 1 naming the
    file, the line and the column; never a traceback, never a changed file."""
    d = _folder(base)
    data, model = _inputs(base, d, data=_cell(base, row, column, value))
    out = d / "r.json"
    rc, line = _run(d, _calibrate(d, data, model, out), capsys, outputs=[out])
    if rc == cli.EXIT_ERROR:
        where = f"{data}, line {base.H + row}, column '{column}'"
        plausibility = f"{data}, column '{column}'"  # a whole column in a wrong unit
        assert where in line or plausibility in line, line
    else:
        assert rc in (cli.EXIT_OK, cli.EXIT_NOT_CONVERGED, cli.EXIT_UNTRUSTED), rc
        assert json.loads(out.read_text())["format"].startswith("cdra_jax.calibr")


def _needs_quotes(value: str) -> bool:
    return any(c in value for c in ',"\r\n')


@fuzz(20)
@given(row=st.integers(1, M), value=st.text(max_size=8))
def test_random_pose_ids_are_read_or_named(base, capsys, row, value):
    d = _folder(base)
    ids = [r[0] for r in base.rows]
    data, model = _inputs(base, d, data=_cell(base, row, "pose", value))
    out = d / "r.json"
    rc, line = _run(d, _calibrate(d, data, model, out), capsys, outputs=[out])
    if value.lstrip().startswith("#") and not _needs_quotes(value):
        assert line == f"error: {data}, line {base.H + row}: comment line after the header" + (
            "; '#' lines are only allowed before it"
        )
    elif rc == cli.EXIT_ERROR:
        other = ids.index(value) + 1 if value in ids else row
        assert f"{data}, line {base.H + max(other, row)}, column 'pose': " in line, line
    else:
        assert rc == cli.EXIT_OK
        assert json.loads(out.read_text())["residuals"][row - 1]["pose"] == value


@fuzz(10)
@given(order=st.permutations(range(14)))
def test_permuted_columns_give_the_same_calibration(base, capsys, order):
    header = [base.header[j] for j in order]
    rows = [[r[j] for j in order] for r in base.rows]
    d = _folder(base)
    data, model = _inputs(base, d, data=_csv_text(base.comments, header, rows))
    out = d / "r.json"
    rc, _ = _run(d, _calibrate(d, data, model, out), capsys, outputs=[out])
    assert rc == 0
    _same_frames(_frames(out), base.frames)


@fuzz(20)
@given(data=st.data())
def test_truncated_files_are_refused_with_the_place(base, capsys, data):
    """A file cut anywhere in its comments, its header or inside its last row."""
    text = base.text
    last_row = text.rstrip("\n").rindex("\n") + 1
    header_end = len(base.comments) + len(",".join(base.header))
    cut = data.draw(
        st.one_of(st.integers(0, header_end - 1), st.integers(last_row + 1, len(text) - 2)),
        label="cut",
    )
    d = _folder(base)
    path, model = _inputs(base, d, data=text[:cut])
    out = d / "r.json"
    rc, line = _run(d, _calibrate(d, path, model, out), capsys, outputs=[out])
    if cut < header_end:
        assert rc == cli.EXIT_ERROR and line.startswith(f"error: {path}"), line
        assert cut <= len(base.comments) or f"line {base.H} (header row)" in line, line
    elif rc == cli.EXIT_ERROR:
        assert f"{path}, line {base.H + M}" in line, line
    else:  # cut inside the last number: still a number, maybe far from the true one
        assert text[cut:].count(",") == 0
        # a changed orientation can pull the unweighted fit worse than nominal: said, exit 4
        assert rc in (0, cli.EXIT_UNTRUSTED), (rc, line)


SPEC_PATHS = [
    ("frames", 0, "xyz", 2),
    ("frames", 1, "rotvec", 0),
    ("frames", 3, "xyz", 0),
    ("modules", 0, "limits", 1, 0),
    ("modules", 1, "limits", 0, 1),
    ("modules", 1, "axis", 1),
    ("modules", 1, "com", 2),
    ("modules", 0, "cables", 3, "base", 1),
    ("modules", 2, "cables", 1, "platform", 2),
    ("modules", 0, "mass"),
    ("modules", 1, "pretension"),
    ("modules", 2, "stiffness"),
    ("gravity", 2),
]
BAD_VALUES = st.one_of(
    st.sampled_from([math.nan, math.inf, -math.inf, 1e300, -1e300, 10**400, "1.0", True, []]),
    st.floats(min_value=1.1e9, allow_infinity=False),
    st.floats(max_value=-1.1e9, allow_infinity=False),
)


def _key_text(spec: dict, path: tuple) -> str:
    """``frames[1] (upper_arm).xyz``-style name of the entry ``path`` leads to."""
    if path[0] == "gravity":
        return "gravity"
    where = f"{path[0]}[{path[1]}] ({spec[path[0]][path[1]]['name']})"
    if path[2] == "cables":
        return f"{where}.cables[{path[3]}]"
    return f"{where}.{path[2]}"


@fuzz(25)
@given(path=st.sampled_from(SPEC_PATHS), value=BAD_VALUES)
def test_bad_model_values_name_the_key(base, capsys, path, value):
    spec = tomllib.loads(base.model_text)
    _spec_edit(path, value)(spec)
    d = _folder(base)
    data, model = _inputs(base, d, model=tomli_w.dumps(spec))
    rc, line = _run(d, _calibrate(d, data, model), capsys)
    assert rc == cli.EXIT_ERROR
    assert line.startswith(f"error: {model}: {_key_text(spec, path)}"), line


def _outside(name: str):
    low, high = BOUNDS[name]
    if isinstance(low, int) and isinstance(high, int):
        return st.one_of(st.integers(max_value=low - 1), st.integers(min_value=high + 1)).map(str)
    return st.one_of(
        st.floats(max_value=low, exclude_max=True),
        st.floats(min_value=high, exclude_min=True),
        st.sampled_from([math.nan, math.inf, -math.inf]),
    ).map(repr)


@fuzz(25)
@given(option=st.sampled_from(["--max-iterations", "--noise-pos", "--noise-rot"]), data=st.data())
def test_calibrate_options_outside_their_bounds_are_refused(base, capsys, option, data):
    value = data.draw(_outside(option.lstrip("-").replace("-", "_")), label="value")
    noise = {"--noise-pos": "0.08", "--noise-rot": "0.001"}
    extra = [f"{option}={value}"]  # "=": argparse reads "-1e+16" alone as an option
    if option != "--max-iterations":
        other = next(k for k in noise if k != option)
        extra += [other, noise[other]]
    d = _folder(base)
    data_path, model = _inputs(base, d)
    rc, line = _run(d, _calibrate(d, data_path, model, None, *extra), capsys)
    assert rc == cli.EXIT_ERROR
    low, high = BOUNDS[option.lstrip("-").replace("-", "_")]
    span = f"[{low}, {high}]" if option == "--max-iterations" else f"[{low:g}, {high:g}]"
    assert line.startswith(f"error: {option} must be ") and f" in {span}, got " in line, line


# --------------------------------------------------------------------------- option bounds

# BOUNDS name -> (command line before the option, option): every bound through one command.
BOUND_OPTIONS: dict[str, tuple[list[str], str]] = {
    "max_iterations": (
        ["calibrate", "--data", "{data}", "--out", "{d}/r.json"],
        "--max-iterations",
    ),
    "poses": (["simulate", "--out", "{d}/s.csv"], "--poses"),
    "trials": (["sweep", *"--noise-pos 0.1 --noise-rot 0.001 --poses 8".split()], "--trials"),
    "chunk": (
        ["sweep", *"--noise-pos 0.1 --noise-rot 0.001 --poses 8 --trials 4".split()],
        "--chunk",
    ),
    "verify": (
        ["sweep", *"--noise-pos 0.1 --noise-rot 0.001 --poses 8 --trials 4".split()],
        "--verify",
    ),
    "cpu_devices": (
        ["sweep", *"--noise-pos 0.1 --noise-rot 0.001 --poses 8 --trials 4".split()],
        "--cpu-devices",
    ),
    "processes": (
        ["sweep", *"--noise-pos 0.1 --noise-rot 0.001 --poses 8 --trials 4".split()],
        "--processes",
    ),
    "timeout": (
        ["sweep", *"--noise-pos 0.1 --noise-rot 0.001 --poses 8 --trials 4".split()],
        "--timeout",
    ),
    "count": (["plan-poses", "--out", "{d}/plan.csv"], "--count"),
    "pool": (["plan-poses", "--count", "4", "--out", "{d}/plan.csv"], "--pool"),
    "folds": (["diagnose", "--data", "{data}", "--out", "{d}/g.json"], "--folds"),
    "noise_pos": (
        ["simulate", "--poses", "4", "--noise-rot", "0.001", "--out", "{d}/s.csv"],
        "--noise-pos",
    ),
    "noise_rot": (
        ["simulate", "--poses", "4", "--noise-pos", "0.1", "--out", "{d}/s.csv"],
        "--noise-rot",
    ),
    "d_v": (["simulate", "--poses", "4", "--out", "{d}/s.csv"], "--d-v"),
    "d_w": (["simulate", "--poses", "4", "--out", "{d}/s.csv"], "--d-w"),
    "cable_noise": (
        ["simulate", "--poses", "4", "--cables", "--out", "{d}/s.csv"],
        "--cable-noise",
    ),
    "occlusion": (["simulate", "--poses", "4", "--points", "--out", "{d}/s.csv"], "--occlusion"),
    "marker_error": (
        ["simulate", "--poses", "4", "--points", "--out", "{d}/s.csv"],
        "--marker-error",
    ),
}
SWEEP_OUT = ["--out", "{d}/sweep.csv"]


def _beyond(name: str) -> list[str]:
    """Values just outside ``BOUNDS[name]`` on both sides (and NaN for a real bound)."""
    low, high = BOUNDS[name]
    if isinstance(low, int) and isinstance(high, int):
        return [str(low - 1), str(high + 1)]
    below = "-1e-300" if low == 0 else f"{low / 2:g}"
    return [below, f"{high * 1.5:g}", "nan"]


BOUND_CASES = [(name, value) for name in BOUNDS for value in _beyond(name)]


def test_every_bound_has_a_command_line():
    assert set(BOUND_OPTIONS) == set(BOUNDS)


@pytest.mark.parametrize(("name", "value"), BOUND_CASES, ids=[f"{n}={v}" for n, v in BOUND_CASES])
def test_options_outside_their_bounds_are_refused_before_any_work(base, capsys, name, value):
    low, high = BOUNDS[name]
    integral = isinstance(low, int) and isinstance(high, int)
    d = _folder(base)
    data, _ = _inputs(base, d)
    prefix, option = BOUND_OPTIONS[name]
    argv = [a.format(d=d, data=data) for a in prefix] + [f"{option}={value}"]
    if argv[0] == "sweep":
        argv += [a.format(d=d) for a in SWEEP_OUT]
    rc, line = _run(d, argv, capsys)
    assert rc == cli.EXIT_ERROR
    span = f"[{low}, {high}]" if integral else f"[{low:g}, {high:g}]"
    kind = "an integer" if integral else "a number"
    assert line.startswith(f"error: {option} must be {kind} in {span}, got "), line


# --------------------------------------------------------------------------- output targets


def _fifo(p: Path) -> Path:
    os.mkfifo(p)
    return p


def _socket(p: Path) -> Path:
    s = socket.socket(socket.AF_UNIX)
    s.bind(str(p))
    s.close()  # the socket file stays
    return p


def _link_to(maker: Callable[[Path], Path]) -> Callable[[Path], Path]:
    def make(p: Path) -> Path:
        target = maker(p.parent / ("target-" + p.name))
        p.symlink_to(target)
        return p

    return make


def _dir(p: Path) -> Path:
    p.mkdir()
    return p


# name -> (argv with {d} {data} {out}, how {out} is made, expected part of the error line)
CALIBRATE = ["calibrate", "--data", "{data}", "--out", "{d}/r.json"]
REFUSED_OUTPUTS = {
    "calibrate --out socket": (
        ["calibrate", "--data", "{data}", "--out", "{out}", "--force"],
        _socket,
        "--out {out}: is a socket, not a regular file",
    ),
    "calibrate --out link to a FIFO": (
        ["calibrate", "--data", "{data}", "--out", "{out}", "--force"],
        _link_to(_fifo),
        "--out {out}: is a FIFO (named pipe), not a regular file",
    ),
    "calibrate --out link to a folder": (
        ["calibrate", "--data", "{data}", "--out", "{out}", "--force"],
        _link_to(_dir),
        "--out {out}: is a folder, expected a file name",
    ),
    "calibrate --out link to a file, no --force": (
        ["calibrate", "--data", "{data}", "--out", "{out}"],
        _link_to(lambda p: (p.write_text("keep"), p)[1]),
        "{out}: file exists; refusing to overwrite it",
    ),
    "calibrate --plot FIFO": (
        [*CALIBRATE, "--plot", "{out}", "--force"],
        _fifo,
        "--plot {out}: is a FIFO",
    ),
    "calibrate --model-out folder": (
        [*CALIBRATE, "--model-out", "{out}", "--force"],
        _dir,
        "--model-out {out}: is a folder",
    ),
    "simulate --out FIFO": (
        ["simulate", "--poses", "4", "--out", "{out}", "--force"],
        _fifo,
        "--out {out}: is a FIFO",
    ),
    "simulate --truth folder": (
        ["simulate", "--poses", "4", "--out", "{d}/s.csv", "--truth", "{out}", "--force"],
        _dir,
        "--truth {out}: is a folder",
    ),
    "sweep --out FIFO": (
        ["sweep", *"--noise-pos 0.1 --noise-rot 0 --poses 8 --trials 4".split(), "--out", "{out}"],
        lambda p: _fifo(p.with_suffix(".csv")),
        "--out {out}: is a FIFO",
    ),
    "sweep --plot socket": (
        ["sweep", *"--noise-pos 0.1 --noise-rot 0 --poses 8 --trials 4 --out {d}/t.csv".split()]
        + ["--plot", "{out}", "--force"],
        _socket,
        "--plot {out}: is a socket",
    ),
    "plan-poses --out socket": (
        ["plan-poses", "--count", "4", "--out", "{out}", "--force"],
        _socket,
        "--out {out}: is a socket",
    ),
    "validate --out FIFO": (
        ["validate", "--data", "{data}", "--out", "{out}", "--force"],
        _fifo,
        "--out {out}: is a FIFO",
    ),
    "diagnose --out link to a socket": (
        ["diagnose", "--data", "{data}", "--out", "{out}", "--force"],
        _link_to(_socket),
        "--out {out}: is a socket",
    ),
    "diagnose --plots a FIFO": (
        ["diagnose", "--data", "{data}", "--out", "{d}/g.json", "--plots", "{out}"],
        _fifo,
        "--plots {out}: exists and is not a folder",
    ),
    "demo --out-dir a file": (["demo", "--out-dir", "{out}"], _fifo, "--out-dir {out}: exists"),
}


@pytest.mark.parametrize("case", list(REFUSED_OUTPUTS))
def test_outputs_that_are_no_regular_file_are_refused_before_any_work(case, capsys):
    argv, make, expected = REFUSED_OUTPUTS[case]
    with tempfile.TemporaryDirectory(prefix="o", dir="/tmp") as tmp:  # short: socket paths
        d = Path(tmp)
        (d / "data.csv").write_text("pose\n")  # never read: the outputs are checked first
        out = make(d / "out.json")
        kinds = {p.name: stat.S_IFMT(p.lstat().st_mode) for p in d.iterdir()}
        subs = {"d": d, "data": d / "data.csv", "out": out}
        rc, line = _run(d, [a.format(**subs) for a in argv], capsys)
        assert rc == cli.EXIT_ERROR
        assert expected.format(**subs) in line, line
        assert kinds == {p.name: stat.S_IFMT(p.lstat().st_mode) for p in d.iterdir()}


@pytest.mark.parametrize("force", [False, True], ids=["new", "force"])
def test_dangling_and_chained_links_are_written_through(base, capsys, force):
    d = _folder(base)
    data, model = _inputs(base, d)
    target = d / "sub" / "result.json"
    target.parent.mkdir()
    if force:
        target.write_text("old")
    (d / "link1.json").symlink_to(target)
    link = d / "link2.json"
    link.symlink_to(d / "link1.json")
    argv = _calibrate(d, data, model, link, *(["--force"] if force else []))
    rc, _ = _run(d, argv, capsys, outputs=[target])
    assert rc == 0 and link.is_symlink() and (d / "link1.json").is_symlink()
    _same_frames(_frames(target), base.frames)


# --------------------------------------------------------------------------- other readers

NESTED_JSON = '{"frames": ' + DEEP + "}"
OTHER_READERS = {
    "errors JSON in UTF-16": (
        ["simulate", "--poses", "4", "--errors", "{bad}", "--out", "{d}/s.csv"],
        '{"frames": {"base": {"vx": 0.5}}}'.encode("utf-16"),
        None,
    ),
    "errors JSON nested deep": (
        ["simulate", "--poses", "4", "--errors", "{bad}", "--out", "{d}/s.csv"],
        NESTED_JSON.encode(),
        None,
    ),
    "errors TOML nested deep": (
        ["simulate", "--poses", "4", "--errors", "{bad}", "--out", "{d}/s.csv"],
        ("x = " + DEEP + "\n").encode(),
        None,
    ),
    "result JSON in Latin-1": (
        ["validate", "--data", "{data}", "--result", "{bad}"],
        '{"format": "cdra_jax.calibration_result", "note": "\xe9"}'.encode("latin-1"),
        None,
    ),
    "result JSON nested deep": (
        ["validate", "--data", "{data}", "--result", "{bad}"],
        NESTED_JSON.encode(),
        None,
    ),
    "result JSON that is a list": (
        ["validate", "--data", "{data}", "--result", "{bad}"],
        b"[1, 2, 3]",
        None,
    ),
    "result JSON with NaN": (
        ["validate", "--data", "{data}", "--result", "{bad}"],
        b'{"format": NaN}',
        None,
    ),
    "errors file with an unknown frame": (
        ["simulate", "--poses", "4", "--errors", "{bad}", "--out", "{d}/s.csv"],
        b'{"frames": {"elbow2": [0, 0, 0, 0, 0, 1e400]}}',
        None,
    ),
}


@pytest.mark.parametrize(
    "case",
    [pytest.param(c, marks=m) if m else c for c, (_, _, m) in OTHER_READERS.items()],
)
def test_bad_result_and_frame_error_files_name_the_file(base, capsys, case):
    argv, content, _ = OTHER_READERS[case]
    d = _folder(base)
    data, _ = _inputs(base, d)
    bad = d / ("bad.toml" if "TOML" in case else "bad.json")
    bad.write_bytes(content)
    rc, line = _run(d, [a.format(d=d, data=data, bad=bad) for a in argv], capsys)
    assert rc == cli.EXIT_ERROR
    assert line.startswith(f"error: {bad}: "), line


# --------------------------------------------------------------------------- concurrency


def test_two_writers_without_force_one_wins_and_the_file_is_whole(tmp_path):
    contents = ["a" * 3_000_000 + "\n", "b" * 3_000_000 + "\n"]
    for k in range(12):
        path = tmp_path / f"out{k}.txt"
        barrier = threading.Barrier(2)
        outcome: list[object] = [None, None]

        def write(i: int, path: Path = path, barrier=barrier, outcome=outcome) -> None:
            barrier.wait()
            try:
                write_text_atomic(path, contents[i])
                outcome[i] = "ok"
            except OutputExistsError as e:
                outcome[i] = e

        threads = [threading.Thread(target=write, args=(i,)) for i in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        winners = [i for i in range(2) if outcome[i] == "ok"]
        assert len(winners) == 1, outcome
        loser = outcome[1 - winners[0]]
        assert isinstance(loser, OutputExistsError) and "file exists" in str(loser)
        assert str(path) in str(loser)
        assert path.read_text() == contents[winners[0]]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f"out{k}.txt" for k in range(12))


def test_two_cli_runs_onto_the_same_output_one_wins(base, capsys):
    """Two ``simulate`` runs (threads in one process) onto one new ``--out``: one writes its
    whole file, the other exits 1 with the "exists" error."""
    d = _folder(base)
    ref = {}
    for seed in ("3", "4"):
        assert (
            cli.main(["simulate", "--poses", str(M), "--seed", seed, "--out", str(d / seed)]) == 0
        )
        ref[seed] = (d / seed).read_text()
    capsys.readouterr()
    out = d / "both.csv"
    barrier = threading.Barrier(2)
    codes: dict[str, int] = {}

    def run(seed: str) -> None:
        barrier.wait()
        codes[seed] = cli.main(["simulate", "--poses", str(M), "--seed", seed, "--out", str(out)])

    threads = [threading.Thread(target=run, args=(s,)) for s in ref]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(codes.values()) == [0, 1], codes
    (winner,) = [s for s, rc in codes.items() if rc == 0]
    assert out.read_text() == ref[winner]
    err = capsys.readouterr().err
    assert f"error: {out}: file exists" in err and "Traceback" not in err
    assert not _temporaries(d)


# --------------------------------------------------------------------------- signals


def _cli_process(argv: list[str], cwd: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "cdra_jax.cli", *argv],
        cwd=cwd,
        env=checkout_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _stderr_lines(proc: subprocess.Popen) -> queue.Queue:
    lines: queue.Queue = queue.Queue()

    def pump() -> None:
        for line in proc.stderr:
            lines.put(line)
        lines.put(None)

    threading.Thread(target=pump, daemon=True).start()
    return lines


def _until_progress(lines: queue.Queue) -> list[str]:
    """The stderr lines up to the first progress line of a sweep (the computing has started)."""
    seen: list[str] = []
    while not any(line.startswith("sweep: ") for line in seen):
        line = lines.get(timeout=120)
        assert line is not None, "".join(seen)  # ended before any progress
        seen.append(line)
    return seen


def _catches_sigterm(pid: int) -> bool:
    """Whether the process has installed its SIGTERM handler (``SigCgt`` of /proc)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    mask = next(int(ln.split()[1], 16) for ln in status.splitlines() if ln.startswith("SigCgt"))
    return bool(mask >> (signal.SIGTERM - 1) & 1)


SWEEP = "--noise-pos 0.08 --noise-rot 0.001 --poses 8 --solvers paper --verify 10 --trials 400"


def _table_rows(path: Path) -> list[str]:
    """The data of a sweep table (its ``#`` lines hold timings)."""
    return [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]


@pytest.mark.slow
def test_sigterm_during_a_sweep_leaves_no_file_and_the_rerun_resumes(tmp_path):
    """SIGTERM after the first chunk: exit 143, no table and no temporary file, only the
    finished chunks; the same command then gives the table of an uninterrupted run."""
    work, ref = tmp_path / "work", tmp_path / "ref"
    work.mkdir()
    ref.mkdir()
    (work / "notes.txt").write_text("keep")
    argv = ["sweep", *SWEEP.split(), "--chunk", "8", "--out", "sweep.csv"]
    reference = _cli_process([*argv, "--no-progress"], ref)  # meanwhile, uninterrupted
    proc = _cli_process(argv, work)
    lines = _stderr_lines(proc)
    try:
        seen = _until_progress(lines)
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=60)
    finally:
        proc.kill()
    while (line := lines.get(timeout=10)) is not None:
        seen.append(line)
    assert rc == cli.EXIT_TERMINATED, "".join(seen)
    assert "Traceback" not in "".join(seen)
    chunks = work / ".sweep.csv.chunks"
    assert sorted(p.name for p in work.iterdir()) == [".sweep.csv.chunks", "notes.txt"]
    assert not _temporaries(work)
    finished = sorted(p.name for p in chunks.glob("*.npz"))
    assert 1 <= len(finished) < 50, finished  # whole chunks only, the sweep not done

    again = subprocess.run(
        [sys.executable, "-m", "cdra_jax.cli", *argv],
        cwd=work,
        env=checkout_env(),
        capture_output=True,
        text=True,
    )
    assert again.returncode == 0, again.stderr
    assert f"resuming from {len(finished)} finished chunk(s)" in again.stderr
    assert reference.wait(timeout=120) == 0, reference.stderr.read()
    assert _table_rows(work / "sweep.csv") == _table_rows(ref / "sweep.csv")
    assert sorted(p.name for p in work.iterdir()) == ["notes.txt", "sweep.csv"]


@pytest.mark.slow
def test_sigterm_during_calibrate_leaves_no_temporary_file(base, tmp_path):
    data = tmp_path / "data.csv"
    data.write_text(base.text)
    proc = _cli_process(["calibrate", "--data", "data.csv", "--out", "r.json"], tmp_path)
    deadline = time.monotonic() + 60
    while not _catches_sigterm(proc.pid) and proc.poll() is None:
        assert time.monotonic() < deadline
        time.sleep(0.02)
    time.sleep(0.5)  # into the compilation and the solver (warm: about 1.5 s in all)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert not _temporaries(tmp_path)
    # -SIGTERM: the signal came after the command had finished, while the interpreter shut down
    # (Python restores the default handler there); the result is then whole
    assert proc.returncode in (cli.EXIT_TERMINATED, cli.EXIT_OK, -signal.SIGTERM), err
    assert "Traceback" not in err
    names = sorted(p.name for p in tmp_path.iterdir())
    if proc.returncode != cli.EXIT_TERMINATED:  # finished first: the whole result
        assert "wrote r.json" in out + err
        assert names == ["data.csv", "r.json"] and json.loads((tmp_path / "r.json").read_text())
    else:
        # terminated: nothing, or (on a loaded machine, the signal arriving after the atomic
        # write and before the exit) the complete result, never a part of one
        assert names in (["data.csv"], ["data.csv", "r.json"])
        if "r.json" in names:
            assert json.loads((tmp_path / "r.json").read_text())["format"]
