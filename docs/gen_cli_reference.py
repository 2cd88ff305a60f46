"""Generate ``reference/cli.md`` from the ``cdra-jax`` argument parser at build time.

Run by the mkdocs-gen-files plugin (see ``mkdocs.yml``). It imports ``build_parser`` from
``cdra_jax.cli``, walks its subcommands and writes each one's ``--help`` text, so the page can
never disagree with the installed command.
"""

from __future__ import annotations

import argparse
import os

import mkdocs_gen_files

from cdra_jax.cli import build_parser


def _subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, argparse.ArgumentParser]]:
    """The (name, parser) pairs of the parser's subcommands, in registration order."""
    out: list[tuple[str, argparse.ArgumentParser]] = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            seen: set[int] = set()
            for name, sub in action.choices.items():
                if id(sub) not in seen:  # aliases map to the same parser
                    seen.add(id(sub))
                    out.append((name, sub))
    return out


def _help(parser: argparse.ArgumentParser) -> str:
    # A fixed width, so the page does not depend on the terminal of whoever builds it.
    os.environ["COLUMNS"] = "88"
    return parser.format_help().rstrip()


def render() -> str:
    parser = build_parser()
    parser.prog = "cdra-jax"
    lines = [
        "# Command-line reference",
        "",
        "Generated from the installed `cdra-jax` argument parser when the documentation is built",
        "(`docs/gen_cli_reference.py`), so it always matches `cdra-jax COMMAND --help`.",
        "",
        "Every command takes `--model M.toml` where it needs a model (default: the embedded 7-DOF",
        "CDRA) and refuses to overwrite an existing output file unless `--force` is given.",
        "Exit codes: see [Errors and exit codes](errors.md).",
        "",
        "## cdra-jax",
        "",
        "```text",
        _help(parser),
        "```",
        "",
    ]
    for name, sub in _subcommands(parser):
        lines += [f"## {name}", "", "```text", _help(sub), "```", ""]
        for inner, subsub in _subcommands(sub):  # e.g. import urdf, import dh, export urdf
            lines += [f"### {name} {inner}", "", "```text", _help(subsub), "```", ""]
    return "\n".join(lines)


with mkdocs_gen_files.open("reference/cli.md", "w") as f:
    f.write(render())
