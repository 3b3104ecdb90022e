"""The doc check: the README's and the docs pages' commands, links and images against the code.

Nothing is run. In the code blocks of ``README.md`` and ``docs/*.md``:

- a ``flyscan ...`` line parses with the CLI's own parser (``flyscan.parse_args``), and
  every option it names is one ``flyscan <command> --help`` lists (argparse would also take
  an abbreviation);
- a ``python -m MODULE ...`` line names a module that exists, and ``python -m MODULE ... --help``
  accepts the line's options and lists each of them;
- a ``make TARGET`` line names a target of the Makefile; ``docker compose -f FILE`` a file;
- a ``python`` block compiles, its imports resolve, and the methods it calls on the objects of
  its ``with`` statements exist and take the arguments given;
- a path into the repository's own folders (``simulator/data/...``) exists;
- any other command line fails: a command the check does not know is a command nobody checks.

In the prose, an inline ```flyscan COMMAND --option``` names a command and options that exist;
every relative link and image exists, and every ``#anchor`` is a heading of its page. The README
shows every ``docs/bench_*.png`` and links every ``docs/*.md``.

``PENDING`` lists the options the README documents before the CLI has them. A line that
uses one is checked without it, for real, and then with it, expected to fail (strict): when the CLI lands these tests pass, strict
xfail fails them, and the entry must be removed from ``PENDING``.
"""
from __future__ import annotations

import ast
import contextlib
import functools
import importlib
import importlib.util
import inspect
import io
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

#: (command, option) -> how many values the option takes: options documented ahead of the CLI.
PENDING: dict = {}
PENDING_REASON = "lands with the pass finisher"
#: Seconds a ``python -m MODULE --help`` may take.
HELP_TIMEOUT_S = 60.0
#: Top-level folders whose paths a command writes to, not reads from.
OUTPUT_DIRS = {"out"}

_FENCE = re.compile(r"^\s*(```+|~~~+)\s*([\w+-]*)")
_CODE_SPAN = re.compile(r"(`+)(.+?)(?<!`)\1(?!`)")
_LINK = re.compile(r"(!?)\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_OPTION = re.compile(r"^--[a-z0-9][a-z0-9-]*")
_ENV = re.compile(r"^[A-Z_][A-Z0-9_]*=")


class PendingOption(AssertionError):
    """A documented option the CLI does not have yet (``PENDING``)."""


@dataclass(frozen=True)
class Line:
    page: Path
    number: int
    text: str
    kind: str  # "command", "python", "inline"

    @property
    def id(self) -> str:
        where = f"{self.page.relative_to(ROOT)}:{self.number}"
        return f"{where}:{self.text}" if self.kind == "inline" else where


def _blocks(page: Path):
    """(kind, first line number, text) of each fenced code block and each prose paragraph."""
    lines = page.read_text(encoding="utf-8").splitlines()
    fence = language = None
    block, start = [], 0
    for number, line in enumerate(lines, 1):
        match = _FENCE.match(line)
        if fence is None and match:
            if block:
                yield "prose", start, block
            fence, language, block, start = match.group(1), match.group(2).lower(), [], number + 1
        elif fence is not None and line.strip().startswith(fence):
            # ```text holds a diagram or a listing, no command
            yield {"python": "python", "text": "text"}.get(language, "code"), start, block
            fence, block = None, []
        elif fence is None and not line.strip():
            if block:
                yield "prose", start, block
            block = []
        else:
            if not block:
                start = number
            block.append(line)
    if block:
        yield ("prose" if fence is None else "code"), start, block


def _collect():
    items = []
    for page in PAGES:
        for kind, start, block in _blocks(page):
            if kind == "python":
                items.append(Line(page, start, "\n".join(block), "python"))
            elif kind == "code":
                pending, first = "", start
                for offset, raw in enumerate(block):
                    if not pending:
                        first = start + offset
                    if raw.rstrip().endswith("\\"):
                        pending += raw.rstrip()[:-1] + " "
                        continue
                    text = (pending + raw).strip()
                    pending = ""
                    if text and not text.startswith("#"):
                        items.append(Line(page, first, text, "command"))
            else:
                paragraph = " ".join(line.strip() for line in block)
                for match in _CODE_SPAN.finditer(paragraph):
                    span = match.group(2).strip()
                    if re.match(r"^(\.venv/bin/)?flyscan(\s|$)", span):
                        items.append(Line(page, start, span, "inline"))
    return items


ITEMS = _collect()


# -- flyscan ---------------------------------------------------------------------------------

@functools.lru_cache(maxsize=None)
def _parse_args():
    """The CLI's own argument parsing, ``flyscan.parse_args`` (or ``_parse_args``): it
    builds the parser and parses, as ``flyscan`` does, without running the command."""
    import flyscan as cli

    for name in ("parse_args", "_parse_args"):
        if callable(getattr(cli, name, None)):
            return getattr(cli, name)
    pytest.fail("flyscan has no parse_args: point tests/test_readme.py at the CLI's "
                "parser builder")


def _run_parser(argv: list[str]) -> tuple[int, str, str]:
    """The CLI's parser on ``argv``: (exit status, stdout, stderr); 0 when it parsed."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            _parse_args()(list(argv))
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 2
            return code, out.getvalue(), err.getvalue()
    return 0, out.getvalue(), err.getvalue()


@functools.lru_cache(maxsize=None)
def _help(command: str | None) -> str:
    code, out, err = _run_parser([command, "--help"] if command else ["--help"])
    assert code == 0, f"flyscan {command or ''} --help exited {code}: {err}"
    return out


@functools.lru_cache(maxsize=None)
def _commands() -> tuple[str, ...]:
    match = re.search(r"\{([a-z,_-]+)\}", _help(None))
    assert match, "flyscan --help lists no commands"
    return tuple(match.group(1).split(","))


def _lists_option(help_text: str, option: str) -> bool:
    return re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", help_text) is not None


def _command_of(argv: list[str]) -> str | None:
    return next((a for a in argv if not a.startswith("-")), None)


def _options(argv: list[str]) -> list[str]:
    found = []
    for arg in argv:
        match = _OPTION.match(arg)
        if match:
            found.append(match.group(0))
    return found


def _pending_in(argv: list[str]) -> list[str]:
    command = _command_of(argv)
    return [o for o in _options(argv) if (command, o) in PENDING]


def _without_pending(argv: list[str]) -> list[str]:
    command, out, skip = _command_of(argv), [], 0
    for arg in argv:
        if skip:
            skip -= 1
            continue
        name = arg.split("=", 1)[0]
        if (command, name) in PENDING:
            skip = 0 if "=" in arg else PENDING[(command, name)]
            continue
        out.append(arg)
    return out


def _check_flyscan(argv: list[str], *, parse: bool, error=AssertionError) -> None:
    command = _command_of(argv)
    if command is not None and not command.startswith("<") and command not in ("...",):
        if command not in _commands():
            raise error(f"flyscan has no command {command!r} (it has {', '.join(_commands())})")
    else:
        command = None
    help_text = _help(command)
    missing = [o for o in _options(argv) if not _lists_option(help_text, o)]
    if missing:
        raise error(f"`flyscan {command or ''} --help` lists no {', '.join(missing)}")
    if parse:
        code, _, err = _run_parser(argv)
        if code != 0:
            raise error(f"flyscan {' '.join(argv)}: the parser exits {code}: {err.strip()}")


def _check_repo_paths(tokens: list[str]) -> None:
    for token in tokens:
        value = token.split("=", 1)[1] if token.startswith("-") and "=" in token else token
        first = value.split("/", 1)[0]
        if ("/" in value and first not in OUTPUT_DIRS and first not in ("", ".", "..")
                and (ROOT / first).is_dir()):
            assert (ROOT / value).exists(), f"{value} does not exist in the repository"


# -- python -m, make, docker -------------------------------------------------------------------

@functools.lru_cache(maxsize=None)
def _make_targets() -> frozenset[str]:
    targets = set()
    for line in (ROOT / "Makefile").read_text(encoding="utf-8").splitlines():
        match = re.match(r"^([A-Za-z0-9_.-]+(?:\s+[A-Za-z0-9_.-]+)*)\s*:(?!=)", line)
        if match:
            targets.update(match.group(1).split())
    return frozenset(targets)


def _check_python_module(args: list[str]) -> None:
    module, rest = args[0], args[1:]
    assert importlib.util.find_spec(module) is not None, f"no module {module}"
    result = subprocess.run([sys.executable, "-m", module, *rest, "--help"], cwd=ROOT,
                            capture_output=True, text=True, timeout=HELP_TIMEOUT_S)
    assert result.returncode == 0, (f"python -m {module} {' '.join(rest)} --help exited "
                                    f"{result.returncode}: {result.stderr.strip()}")
    missing = [o for o in _options(rest) if not _lists_option(result.stdout, o)]
    assert not missing, f"python -m {module} --help lists no {', '.join(missing)}"


def _check_command(line: Line) -> None:
    tokens = shlex.split(line.text, comments=True)
    while tokens and _ENV.match(tokens[0]):
        tokens.pop(0)
    assert tokens, f"no command in {line.text!r}"
    program, args = Path(tokens[0]).name, tokens[1:]
    _check_repo_paths(args)
    if program == "flyscan":
        pending = _pending_in(args)
        _check_flyscan(_without_pending(args), parse=True)
        if pending:
            _check_flyscan(args, parse=True, error=PendingOption)
    elif program.startswith("python") and args[:1] == ["-m"] and len(args) > 1:
        _check_python_module(args[1:])
    elif program == "make":
        unknown = [t for t in args if not t.startswith("-") and t not in _make_targets()]
        assert args and not unknown, f"the Makefile has no target {unknown or args}"
    elif program == "docker" and "-f" in args:
        compose = args[args.index("-f") + 1]
        assert (ROOT / compose).is_file(), f"{compose} does not exist"
    else:
        pytest.fail(f"{line.id}: a command line the doc check does not know: {line.text!r}")


# -- python blocks ---------------------------------------------------------------------------

def _check_python_block(line: Line) -> None:
    tree = ast.parse(line.text)
    names = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            module = importlib.import_module(node.module)
            for alias in node.names:
                assert hasattr(module, alias.name), f"{node.module} has no {alias.name}"
                names[alias.asname or alias.name] = getattr(module, alias.name)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                names[alias.asname or alias.name] = importlib.import_module(alias.name)
    instances = {}
    for node in ast.walk(tree):
        if isinstance(node, (ast.With, ast.AsyncWith)):
            for item in node.items:
                call = item.context_expr
                if (isinstance(call, ast.Call) and isinstance(call.func, ast.Name)
                        and call.func.id in names and isinstance(item.optional_vars, ast.Name)):
                    cls = names[call.func.id]
                    _bind(cls, call, f"{call.func.id}(...)")
                    instances[item.optional_vars.id] = cls
    assert instances or not names, "the block's objects were not recognised"
    for node in ast.walk(tree):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                and isinstance(node.func.value, ast.Name) and node.func.value.id in instances):
            cls, attr = instances[node.func.value.id], node.func.attr
            assert hasattr(cls, attr), f"{cls.__name__} has no method {attr}"
            _bind(getattr(cls, attr), node, f"{cls.__name__}.{attr}(...)", method=True)


def _bind(target, call: ast.Call, what: str, *, method: bool = False) -> None:
    signature = inspect.signature(target)
    args = [None] * len(call.args)
    kwargs = {k.arg: None for k in call.keywords if k.arg is not None}
    try:
        signature.bind(*([None] if method else []), *args, **kwargs)
    except TypeError as exc:
        raise AssertionError(f"{what}: {exc}") from None


# -- the tests -------------------------------------------------------------------------------

def _param(line: Line):
    pending = []
    if line.kind in ("command", "inline"):
        try:
            tokens = shlex.split(line.text, comments=True)
        except ValueError:
            tokens = line.text.split()
        while tokens and _ENV.match(tokens[0]):
            tokens.pop(0)
        if tokens and Path(tokens[0]).name == "flyscan":
            pending = _pending_in(tokens[1:])
    marks = [pytest.mark.xfail(strict=True, raises=PendingOption,
                               reason=f"{PENDING_REASON}: {', '.join(pending)}")] if pending else []
    return pytest.param(line, id=line.id, marks=marks)


@pytest.mark.parametrize("line", [_param(i) for i in ITEMS if i.kind == "command"])
def test_command_line(line):
    _check_command(line)


@pytest.mark.parametrize("line", [_param(i) for i in ITEMS if i.kind == "inline"])
def test_inline_flyscan_command(line):
    tokens = line.text.split()
    args = tokens[1:]
    pending = _pending_in(args)
    _check_flyscan(_without_pending(args), parse=False)
    if pending:
        _check_flyscan(args, parse=False, error=PendingOption)


@pytest.mark.parametrize("line", [_param(i) for i in ITEMS if i.kind == "python"])
def test_python_block(line):
    _check_python_block(line)


def _slug(heading: str) -> str:
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


@functools.lru_cache(maxsize=None)
def _anchors(page: Path) -> frozenset[str]:
    seen: dict[str, int] = {}
    anchors = set()
    for kind, _, block in _blocks(page):
        if kind != "prose":
            continue
        for line in block:
            match = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
            if match:
                slug = _slug(match.group(1))
                count = seen.get(slug, 0)
                anchors.add(slug if count == 0 else f"{slug}-{count}")
                seen[slug] = count + 1
    return frozenset(anchors)


def _links(page: Path):
    for kind, start, block in _blocks(page):
        if kind != "prose":
            continue
        paragraph = " ".join(line.strip() for line in block)
        paragraph = _CODE_SPAN.sub("", paragraph)
        for match in _LINK.finditer(paragraph):
            yield start, bool(match.group(1)), match.group(2)


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_links_and_images_exist(page):
    broken = []
    for number, image, target in _links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        linked = (page.parent / path).resolve() if path else page
        if not linked.exists():
            broken.append(f"line {number}: {'image' if image else 'link'} {target}: no such file")
        elif anchor and linked.suffix == ".md" and anchor not in _anchors(linked):
            broken.append(f"line {number}: {target}: no heading #{anchor} in {linked.name}")
    assert not broken, "\n".join(broken)


def test_the_readme_shows_every_chart_and_links_every_page():
    readme = ROOT / "README.md"
    targets = {(readme.parent / t.partition("#")[0]).resolve() for _, _, t in _links(readme)
               if not re.match(r"^[a-z][a-z0-9+.-]*:", t)}
    charts = sorted((ROOT / "docs").glob("bench_*.png"))
    pages = sorted((ROOT / "docs").glob("*.md"))
    assert charts and pages
    missing = [p.name for p in [*charts, *pages] if p.resolve() not in targets]
    assert not missing, f"the README shows or links none of {missing}"


def test_the_readme_stays_short():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    # about 300 lines, with a worked case of acting on the pose
    assert len(lines) < 320, f"README.md has {len(lines)} lines (under 320)"


def test_the_check_found_the_commands():
    """The parser of this file found what the README holds (a broken fence would hide them)."""
    readme = [i for i in ITEMS if i.page.name == "README.md"]
    kinds = {i.kind for i in readme}
    assert kinds == {"command", "inline", "python"}, kinds
    programs = {Path(shlex.split(i.text, comments=True)[0]).name
                for i in readme if i.kind == "command" and not _ENV.match(i.text)}
    assert {"flyscan", "make"} <= programs, programs
