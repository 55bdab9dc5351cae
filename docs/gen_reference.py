"""MkDocs hook: the reference pages' generated parts, rebuilt from the code on every build.

A page holds a marker line ``<!-- bonecad:NAME -->`` where the generated Markdown goes:

- ``cli``: every command, sub-command and flag of ``bonecad.run.cli.build_parser()`` (walked, so a
  command added to the parser appears without an edit here), with its description, example and help;
- ``settings``: every setting of ``bonecad/data/defaults.toml`` with its default and its comment;
- ``errors``: every exception class bonecad raises on purpose (``bonecad.errors`` and its subclasses
  anywhere in the package) and the exit statuses of ``bonecad.run.cli``;
- ``exporters``: every file an exporter of ``bonecad.export.registry`` writes, with its docstring;
- ``report-schema``: the ``report.json`` schema from ``bonecad.export.report``'s docstring.

The nav lists user guides other branches add; a listed page that does not exist yet is dropped from the
nav here (``validation: nav: not_found: info`` in mkdocs.yml lets the build reach this hook).
"""
from __future__ import annotations

import argparse
import ast
import importlib
import inspect
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

MARKER = re.compile(r"^<!-- bonecad:([a-z-]+) -->$", re.M)


# -- commands -----------------------------------------------------------------------------------------------

def _subparsers(parser: argparse.ArgumentParser) -> list[tuple[str, argparse.ArgumentParser]]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return list(action.choices.items())
    return []


def _flag_row(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    formatter = parser._get_formatter()
    if action.option_strings:
        metavar = formatter._format_args(action, action.dest.upper()) if action.nargs != 0 else ""
        name = ", ".join(f"`{o}{' ' + metavar if metavar else ''}`" for o in action.option_strings)
    else:
        name = f"`{formatter._metavar_formatter(action, action.dest)(1)[0]}`"
    text = formatter._expand_help(action) if action.help else ""
    if action.choices and not isinstance(action, argparse._SubParsersAction):
        text += f" (one of: {', '.join(f'`{c}`' for c in action.choices)})"
    if action.required:
        text += " **required**"
    return f"| {name} | {_cell(text)} |"


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")


def _command(name: str, parser: argparse.ArgumentParser, level: int) -> list[str]:
    lines = [f"{'#' * level} `{name}`", ""]
    if parser.description:
        lines += [parser.description.replace("%%", "%"), ""]
    lines += ["```text", parser.format_usage().strip(), "```", ""]
    rows = [_flag_row(parser, a) for a in parser._actions
            if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))]
    if rows:
        lines += ["| argument | meaning |", "|---|---|", *rows, ""]
    if parser.epilog:
        lines += ["Example:", "", "```sh", parser.epilog.strip().removeprefix("example:").strip(), "```", ""]
    for sub_name, sub in _subparsers(parser):
        lines += _command(f"{name} {sub_name}", sub, level + 1)
    return lines


def cli_markdown() -> str:
    """Every command and flag of the ``bonecad`` parser, as Markdown."""
    from bonecad.run.cli import build_parser

    parser = build_parser()
    lines = [parser.description or "", "", "```text", parser.format_usage().strip(), "```", ""]
    lines += ["| argument | meaning |", "|---|---|"]
    lines += [_flag_row(parser, a) for a in parser._actions
              if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))]
    if parser.epilog:
        lines += ["", "Example:", "", "```sh", parser.epilog.strip().removeprefix("example:").strip(), "```"]
    lines += [""]
    for name, sub in _subparsers(parser):
        lines += _command(f"bonecad {name}", sub, 2)
    return "\n".join(lines)


# -- settings -----------------------------------------------------------------------------------------------

DEFAULTS = ROOT / "bonecad" / "data" / "defaults.toml"


def settings_entries(path: Path = DEFAULTS) -> list[tuple[str, str, str, str]]:
    """(section, key, value as written, the comment above it) for every setting of a TOML file with
    comments; a key right after another, with no comment of its own, shares the one above both (and
    says so rather than repeating it)."""
    entries: list[tuple[str, str, str, str]] = []
    section, comment, last = "", [], ""
    after_block = False
    lines = path.read_text().splitlines()
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        i += 1
        if line.startswith("#"):
            text = line[1:]
            # an indented comment line (a table or list in the file) keeps its own line, and so does the
            # line after such a block
            indented = text.startswith("   ")
            comment.append(("<br>" if comment and (indented or after_block) else "") + text.strip())
            after_block = indented
        elif line.startswith("["):
            section, comment, last = line.strip("[]").strip(), [], ""
        elif "=" in line and section:
            key, value = (s.strip() for s in line.split("=", 1))
            while value.count("[") > value.count("]") or value.count("{") > value.count("}"):
                value += " " + lines[i].split("#")[0].strip()  # a value written over several lines
                i += 1
            text = " ".join(comment) or (f"(with `{last}`, above)" if last else "")
            entries.append((section, key, value, text))
            comment, last, after_block = [], (key if comment else last), False
        elif not line:
            last = ""
    return entries


def _section_intro(path: Path = DEFAULTS) -> dict[str, str]:
    """The comment right below each ``[section]`` line that the first key does not take (a blank line
    between them)."""
    intro: dict[str, str] = {}
    section, block = "", []
    for line in path.read_text().splitlines():
        s = line.strip()
        if s.startswith("["):
            section, block = s.strip("[]"), []
        elif s.startswith("#"):
            block.append(s.lstrip("#").strip())
        elif not s and section and block and section not in intro:
            intro[section] = " ".join(block)
            block = []
        elif s:
            intro.setdefault(section, "")
            block = []
    return intro


def settings_markdown() -> str:
    """Every setting of defaults.toml: section, key, default, and the comment giving its reason."""
    lines: list[str] = []
    intro = _section_intro()
    section = None
    for sec, key, value, comment in settings_entries():
        if sec != section:
            section = sec
            lines += [f"## `[{sec}]`", ""]
            if intro.get(sec):
                lines += [intro[sec], ""]
        lines += [f"`{key}` = `{value}`", f":   {comment or '(no comment)'}", ""]
    return "\n".join(lines)


# -- errors -------------------------------------------------------------------------------------------------

def error_classes() -> list[type]:
    """bonecad's exception classes: those of bonecad.errors and every subclass defined in the package."""
    import bonecad.errors as errors

    names: list[tuple[str, str]] = []
    for path in sorted((ROOT / "bonecad").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and any(
                    getattr(b, "id", getattr(b, "attr", "")).endswith("Error") for b in node.bases):
                module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
                names.append((module.removesuffix(".__init__"), node.name))
    classes = [getattr(importlib.import_module(m), n) for m, n in names]
    return [c for c in classes if issubclass(c, errors.BonecadError)]


def errors_markdown() -> str:
    from bonecad.run import cli

    lines = ["| class | module | kind of | exit status | meaning |", "|---|---|---|---|---|"]
    from bonecad.errors import InputError

    for cls in error_classes():
        bases = ", ".join(f"`{b.__name__}`" for b in cls.__bases__)
        status = cli.EXIT_BAD_INPUT if issubclass(cls, InputError) else cli.EXIT_INTERNAL
        doc = inspect.getdoc(cls) or ""
        lines.append(f"| `{cls.__name__}` | `{cls.__module__}` | {bases} | {status} | {_cell(doc)} |")
    lines += ["", "| exit status | when |", "|---|---|",
              f"| {cli.EXIT_OK} | success: every file written |",
              f"| {cli.EXIT_BAD_INPUT} | bad input (`InputError` and its subclasses): one line `bonecad: error: FILE: "
              "problem` on stderr, no output written |",
              f"| {cli.EXIT_INTERNAL} | an internal failure (any other error): one line `bonecad: internal error: "
              "...`; `--verbose` adds the traceback |",
              "| 130 | interrupted by Ctrl-C (SIGINT): children stopped, nothing written |",
              "| 143 | stopped by SIGTERM: the same |", ""]
    return "\n".join(lines)


# -- output files -------------------------------------------------------------------------------------------

def exporter_rows() -> list[tuple[str, str, str, str]]:
    """(kind, format, module, what the file holds) for every registered exporter."""
    from bonecad.export import registry

    for module in registry.FORMAT_MODULES:
        importlib.import_module(module)
    rows = []
    for (kind, fmt), fn in registry.EXPORTERS.items():
        doc = inspect.getdoc(fn) or (inspect.getdoc(sys.modules[fn.__module__]) or "").split("\n\n")[0]
        rows.append((kind, fmt, fn.__module__, doc))
    return rows


def exporters_markdown() -> str:
    lines = ["| result | format | written by | what it holds |", "|---|---|---|---|"]
    lines += [f"| `{k}` | `{f}` | `{m}` | {_cell(d)} |" for k, f, m, d in exporter_rows()]
    return "\n".join(lines + [""])


def report_schema_markdown() -> str:
    import bonecad.export.report as report

    doc = inspect.getdoc(report) or ""
    schema = doc.split("::", 1)[1].split("\n\n", 2)[1]
    return "```text\n" + inspect.cleandoc(schema) + "\n```\n"


# -- Python API and measurements --------------------------------------------------------------------------

def api_markdown() -> str:
    """mkdocstrings directives for the public API: ``bonecad.__all__`` (each name where it is defined),
    the T-spline library ``bonecad.tspline`` and ``bonecad.STAGES``."""
    import bonecad

    own, elsewhere = [], []
    for name in bonecad.__all__:
        obj = getattr(bonecad, name)
        if name.startswith("__") or inspect.ismodule(obj):
            continue
        (own if obj.__module__ == "bonecad" else elsewhere).append(f"{obj.__module__}.{obj.__qualname__}")
    lines = ["## The package: `import bonecad`", "", "::: bonecad", "    options:", "      show_root_heading: false",
             "      members:", *[f"        - {n.rsplit('.', 1)[1]}" for n in own], ""]
    for path in elsewhere:
        lines += [f"::: {path}", *(["    options:", "      members: false"] if path.endswith("Error") else []), ""]
    lines += ["## The T-spline library: `bonecad.tspline`", "", "::: bonecad.tspline", "    options:",
              "      show_root_heading: false", "      members: false", ""]
    import bonecad.tspline as ts

    for n in ts.__all__:  # each where it is defined
        obj = getattr(ts, n)
        if inspect.ismodule(obj):
            lines += [f"::: {obj.__name__}", "    options:", "      members: false", ""]
        else:
            lines += [f"::: {obj.__module__}.{obj.__qualname__}", ""]
    lines += ["", "## The stages", ""]
    for entry in bonecad.STAGES:
        lines += [f"::: {entry.replace(':', '.')}", ""]
    return "\n".join(lines)


def parameters_markdown() -> str:
    """The table of ``bonecad measure``'s parameters: name, unit, definition."""
    from bonecad.anatomy.morphometry import PARAMETERS

    rows = [f"| `{n}` | {u} | {_cell(d)} |" for n, u, d in PARAMETERS]
    return "\n".join(["| parameter | unit | definition |", "|---|---|---|", *rows, ""])


GENERATORS = {"api": api_markdown, "parameters": parameters_markdown, "cli": cli_markdown,
              "settings": settings_markdown, "errors": errors_markdown,
              "exporters": exporters_markdown, "report-schema": report_schema_markdown}


# -- MkDocs events ------------------------------------------------------------------------------------------

def on_config(config):
    """Import bonecad from this checkout, not from another installed copy (MkDocs restores ``sys.path``
    after loading a hook, so this is done here)."""
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    return config


def on_page_markdown(markdown: str, page, config, files) -> str:
    def generate(match: re.Match) -> str:
        return GENERATORS[match.group(1)]()

    return MARKER.sub(generate, markdown)


def on_nav(nav, config, files):
    """Drop nav entries for pages not written yet (a guide another branch adds)."""
    from mkdocs.structure.nav import Link, Section

    def keep(items: list) -> list:
        kept = []
        for item in items:
            if isinstance(item, Link) and item.url.endswith(".md"):
                continue
            if isinstance(item, Section):
                item.children = keep(item.children)
            kept.append(item)
        return kept

    nav.items = keep(nav.items)
    return nav
