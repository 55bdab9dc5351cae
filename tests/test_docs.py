"""The documentation site (``mkdocs.yml``, ``docs/``) and the README.

The site builds in strict mode (no broken link, no missing page or reference); its reference holds every
command and flag of the parser, every setting of ``defaults.toml``, every error class and every file the
pipeline writes; every public function has a docstring and a place in the API reference; the python
blocks of the getting-started page and the README run; the built pages load in headless Chromium with no
console message.
"""
from __future__ import annotations

import argparse
import ast
import importlib
import inspect
import os
import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

import bonecad
from bonecad.run.cli import build_parser

from .test_report_browser import CHROMIUM, chromium, console_messages

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """``mkdocs build --strict`` of this checkout into a temporary folder (about 10-15 s)."""
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NO_MKDOCS_2_WARNING": "1"}
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    return out


class _Sections(HTMLParser):
    """The text of a page's article, cut at its headings: [(heading text, text up to the next heading)]."""

    def __init__(self) -> None:
        super().__init__()
        self.sections: list[list[str]] = [["", ""]]
        self._in_heading = False
        self._skip = 0

    def handle_starttag(self, tag, attrs):
        if re.fullmatch(r"h[1-6]", tag):
            self._in_heading = True
            self.sections.append(["", ""])
        if tag in ("script", "style"):
            self._skip += 1

    def handle_endtag(self, tag):
        if re.fullmatch(r"h[1-6]", tag):
            self._in_heading = False
        if tag in ("script", "style"):
            self._skip -= 1

    def handle_data(self, data):
        if not self._skip:
            self.sections[-1][0 if self._in_heading else 1] += data


def sections(page: Path) -> dict[str, str]:
    html = page.read_text()
    article = html[html.index("<article"):html.index("</article>")]
    parser = _Sections()
    parser.feed(article)
    return {" ".join(h.replace("¶", "").split()): text for h, text in parser.sections}


def _commands(parser: argparse.ArgumentParser, prefix: str = "bonecad"):
    """(command path, its parser) for every command and sub-command, depth first."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield f"{prefix} {name}", sub
                yield from _commands(sub, f"{prefix} {name}")


COMMANDS = list(_commands(build_parser()))


@pytest.mark.slow
def test_the_reference_lists_every_command_and_flag(site):
    """Each command has its own section, holding each of its flags and an example."""
    text = sections(site / "reference" / "cli.html")
    missing = []
    for name, parser in COMMANDS:
        if name not in text:
            missing.append(name)
            continue
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            for option in action.option_strings:
                if option not in text[name]:
                    missing.append(f"{name} {option}")
            if not action.option_strings and not isinstance(action, argparse._SubParsersAction):
                if (action.metavar or action.dest) not in text[name]:
                    missing.append(f"{name} {action.dest}")
        if not _subcommands(parser) and "Example" not in text[name]:
            missing.append(f"{name}: no example")
    assert not missing, missing


def _subcommands(parser: argparse.ArgumentParser) -> bool:
    return any(isinstance(a, argparse._SubParsersAction) for a in parser._actions)


def test_every_command_has_an_example_in_its_help():
    """``bonecad COMMAND --help`` ends with an example of the command itself."""
    lacking = [name for name, parser in COMMANDS
               if not _subcommands(parser) and f"example: {name}" not in (parser.epilog or "")]
    assert not lacking
    assert "tibia" in build_parser().description and "femur" in build_parser().description


@pytest.mark.slow
def test_the_reference_lists_every_setting(site):
    """Every key of defaults.toml, in its section, with its default and the comment above it."""
    defaults = tomllib.loads((ROOT / "bonecad" / "data" / "defaults.toml").read_text())
    text = sections(site / "reference" / "settings.html")
    missing = []
    for section, values in defaults.items():
        body = text.get(f"[{section}]")
        if body is None:
            missing.append(f"[{section}]")
            continue
        missing += [f"[{section}] {key}" for key in values if re.search(rf"\b{re.escape(key)}\b = ", body) is None]
    assert not missing, missing
    # the comments come along: one of the working copy's measurements, from its comment in the file
    assert "quadric edge collapse" in text["[mesh]"]


def _error_classes() -> list[str]:
    """Every exception class defined in the package whose base's name ends in Error."""
    names = []
    for path in sorted((ROOT / "bonecad").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and (node.name.endswith("Error") or any(
                    getattr(b, "id", "").endswith("Error") for b in node.bases)):
                names.append(node.name)
    return names


@pytest.mark.slow
def test_the_reference_lists_every_error_and_exit_status(site):
    text = (site / "reference" / "errors.html").read_text()
    classes = _error_classes()
    assert {"BonecadError", "InputError", "FitError", "KernelError", "TSMError"} <= set(classes)
    assert [c for c in classes if f"<code>{c}</code>" not in text] == []
    for status in ("0", "1", "2", "130", "143"):
        assert f"<td>{status}</td>" in text, status


@pytest.mark.slow
def test_the_reference_describes_every_output_file(site, phantom_run):
    """Every file ``bonecad reconstruct`` writes (the phantom's run) is named on the output-files page."""
    text = (site / "reference" / "outputs.html").read_text()
    written = sorted(p.name for p in phantom_run.iterdir())
    assert written and [name for name in written if name not in text] == []
    from bonecad.export import registry

    registry.formats("report")  # imports every format module
    assert [fn.__module__ for fn in registry.EXPORTERS.values() if fn.__module__ not in text] == []


def _public_api() -> dict[str, object]:
    """bonecad's public API: ``bonecad.__all__``, ``bonecad.tspline.__all__`` and ``bonecad.STAGES``."""
    import bonecad.tspline

    api = {f"bonecad.{n}": getattr(bonecad, n) for n in bonecad.__all__ if not n.startswith("__")}
    api |= {f"bonecad.tspline.{n}": getattr(bonecad.tspline, n) for n in bonecad.tspline.__all__}
    for entry in bonecad.STAGES:
        module, name = entry.split(":")
        api[entry] = getattr(importlib.import_module(module), name)
    return api


def test_every_public_function_has_a_docstring():
    """The public API's functions, classes and modules, and the public methods and properties of its
    classes."""
    undocumented = []
    for name, obj in _public_api().items():
        if not inspect.getdoc(obj):
            undocumented.append(name)
        if inspect.isclass(obj):
            for member, value in vars(obj).items():
                fn = value.fget if isinstance(value, property) else getattr(value, "__func__", value)
                if not member.startswith("_") and inspect.isfunction(fn) and not fn.__doc__:
                    undocumented.append(f"{name}.{member}")
    assert not undocumented, undocumented


def test_the_names_the_docs_use_import():
    """``bonecad.tspline`` is a real module (not only an attribute), the same as ``bonecad.tspline`` the
    attribute, and every STAGES entry resolves."""
    from bonecad.tspline import open_region, read_tspline, tsm, write_tspline  # noqa: F401

    assert importlib.import_module("bonecad.tspline") is bonecad.tspline
    assert callable(tsm.read) and callable(tsm.census)
    assert len(_public_api()) > len(bonecad.__all__)


@pytest.mark.slow
def test_the_api_reference_covers_the_public_api(site):
    text = (site / "reference" / "api.html").read_text()
    missing = [name for name, obj in _public_api().items()
               if not inspect.ismodule(obj) and not isinstance(obj, str)
               and f'id="{getattr(obj, "__module__", "")}.{getattr(obj, "__qualname__", "")}"' not in text
               and f'id="{name.replace(":", ".")}"' not in text]
    assert not missing, missing


def python_blocks(markdown: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", markdown, flags=re.M | re.S)


def test_the_getting_started_code_runs(tmp_path, monkeypatch):
    """Every python block of the getting-started page that is not marked ``# illustration`` runs, in
    order, in one namespace (at least one does; about 10 s, on the phantom)."""
    blocks = [b for b in python_blocks((DOCS / "getting-started.md").read_text())
              if not b.startswith("# illustration")]
    assert blocks
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    for block in blocks:
        exec(compile(block, "getting-started.md", "exec"), namespace)
    assert namespace["frame"].side == "right" and "plateau_width_mm" in namespace["values"]


@pytest.mark.slow
def test_the_readme_example_runs(tmp_path, monkeypatch, phantom):
    """The README's python lines run as written after the demo (its phantom.stl; about 30 s)."""
    (block,) = python_blocks((ROOT / "README.md").read_text())
    assert len(block.strip().splitlines()) <= 5
    (tmp_path / "demo-out").mkdir()
    phantom.to_trimesh().export(tmp_path / "demo-out" / "phantom.stl")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(block, "README.md", "exec"), namespace)
    assert (tmp_path / "my-out" / "tspline.step").is_file()


def test_the_readme_is_short_and_links_into_the_docs():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 150
    # the two commands, exactly (.ci/run runs the second)
    assert "./scripts/setup.sh && .venv/bin/bonecad demo --out demo-out\n" in text
    assert "./scripts/setup.sh && .venv/bin/python -m pytest\n" in text
    assert "./scripts/setup.sh && .venv/bin/python -m pytest" in (ROOT / ".ci" / "run").read_text()
    assert ".venv/bin/mkdocs build --strict" in text
    # every top-level command in the commands table, and every relative link to a file that exists
    top = {name.split()[1] for name, _ in COMMANDS}
    assert [c for c in top if f"`bonecad {c}" not in text] == []
    links = re.findall(r"\]\(([^)#]+)\)", text)
    assert links and [link for link in links if not link.startswith("http") and not (ROOT / link).exists()] == []


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="Chromium is absent (scripts/setup.sh installs Debian's chromium)")
@pytest.mark.parametrize("page", ["getting-started", "reference/api"])
def test_pages_load_in_chromium_without_console_messages(site, page):
    html = site / f"{page}.html"
    run = chromium("--dump-dom", html.as_uri())
    assert not console_messages(run.stderr), console_messages(run.stderr)[:5]
    assert "<article" in run.stdout and "bonecad" in run.stdout


def test_the_published_ranges_the_measurements_are_tested_against_are_in_the_docs():
    """tests/test_morphometry.py's ranges are the ones the anatomy-literature page states, each with its
    sources; the parameters it leaves untested are named there too."""
    from .test_morphometry import PUBLISHED, UNSOURCED

    page = (DOCS / "validation" / "anatomy-literature.md").read_text()
    stated = [name for name, (lo, hi) in PUBLISHED.items()
              if not any(f"{a}-{b}" in page for a, b in ((f"{lo:g}", f"{hi:g}"), (f"{lo:.1f}", f"{hi:.1f}")))]
    assert not stated, f"ranges not on the page: {stated}"
    assert [name for name in UNSOURCED if name not in page] == []
