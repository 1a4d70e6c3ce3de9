"""Conventions of the code that a reader relies on, checked over the source text.

* no function longer than 120 lines outside the studies (a long function is split into
  named steps);
* no public function takes more than 12 parameters (what belongs together travels as one
  parameter object, a NamedTuple or a frozen dataclass); a command's callback takes one
  parameter per option and is exempt;
* every public function, method and class of ``src/ajtwin`` has a docstring;
* nothing points outside the repository (the model is documented in
  ``docs/reference/model.md`` and cited as "model reference §N");
* the code and the tests carry no traces of how the work was organised: no issue
  numbers, finding codes, dates of work, "agent" or "helper", and "session" only in its
  two technical meanings (a live print's log in the registry, an OPC UA session).
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "src" / "ajtwin"
TESTS = ROOT / "tests"
MAX_LINES = 120
MAX_PARAMETERS = 12

#: The patterns below are assembled from parts so that this file does not match itself.
_NOTE = "SP" + "EC"
OUTSIDE = re.compile(r"\.\./shared|\bshared/" + _NOTE + r"|" + _NOTE + r"\.md|\b" + _NOTE + r" ?§")
ISSUE = re.compile(r"\b" + "iss" + r"ues?\s*#?\d+", re.I)
FINDING = re.compile(r"\b" + "find" + r"ings?\s+[A-Z]\d+\b")
CODE_NAME = re.compile(r"\bdef test_[A-Z]\d+_")
WORK_WORDS = re.compile(r"\b(" + "age" + "nts?|" + "hel" + r"pers?)\b", re.I)
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
SESSION = re.compile(r"sess" + "ion", re.I)
#: Where "session" is a term of the code: the live twin's sessions (a print followed live,
#: table ``live_sessions`` of the registry), OPC UA sessions, PostgreSQL's session settings
#: and pytest's session scope (one PostgreSQL server a test run: tests/conftest.py).
SESSION_FILES = {
    "src/ajtwin/cli/live.py",
    "src/ajtwin/cli/store.py",
    "src/ajtwin/store/copy.py",
    "src/ajtwin/store/database.py",
    "src/ajtwin/store/queries.py",
    "src/ajtwin/store/schema.py",
    "src/ajtwin/studies/lab_faults.py",
    "src/ajtwin/web/watcher.py",
    "tests/conftest.py",
    "tests/test_lab_faults.py",
    "tests/test_store_copy.py",
    "tests/test_store_postgres.py",
    "src/ajtwin/cli/machine.py",
    "src/ajtwin/engine/fleet.py",
    "src/ajtwin/engine/ingest.py",
    "src/ajtwin/engine/parts.py",
    "src/ajtwin/live/control_link.py",
    "src/ajtwin/live/link.py",
    "src/ajtwin/live/printer_server.py",
    "src/ajtwin/store/archive.py",
    "src/ajtwin/store/compaction.py",
    "src/ajtwin/store/live_log.py",
    "src/ajtwin/store/registry.py",
    "src/ajtwin/studies/live_storage.py",
    "tests/test_control_live.py",
    "tests/test_docs.py",
    "tests/test_live.py",
    "tests/test_live_link_faults.py",
    "tests/test_live_opcua.py",
    "tests/test_store_live_tables.py",
}
THIS = Path(__file__).resolve()


def _python_files(*roots: Path):
    for root in roots:
        yield from sorted(p for p in root.rglob("*.py") if p.resolve() != THIS)


def _text_files():
    """Every text file of src/, tests/, benchmarks/ and scripts/, the Makefile, pyproject."""
    suffixes = {".py", ".toml", ".md", ".js", ".html", ".css", ".cfg", ".txt", ".json", ".sh"}
    for name in ("src", "tests", "benchmarks", "scripts"):
        for path in sorted((ROOT / name).rglob("*")):
            if path.suffix in suffixes and path.is_file() and path.resolve() != THIS:
                if ".egg-info" not in str(path) and "fuzz_corpus" not in path.parts:
                    yield path
    yield ROOT / "Makefile"
    yield ROOT / "pyproject.toml"


def _where(path: Path, line: int) -> str:
    return f"{path.relative_to(ROOT)}:{line}"


def test_no_function_over_120_lines_outside_the_studies():
    long = []
    for path in _python_files(PACKAGE):
        if path.parent.name == "studies":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_LINES:
                    long.append(f"{_where(path, node.lineno)} {node.name}: {n} lines")
    assert not long, "split into named steps:\n" + "\n".join(long)


def parameter_count(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """A function's parameters: ``self``/``cls`` not counted, ``*args``, ``**kwargs`` one each."""
    args = node.args
    names = [a.arg for a in (*args.posonlyargs, *args.args, *args.kwonlyargs)]
    if names and names[0] in ("self", "cls"):
        names = names[1:]
    return len(names) + (args.vararg is not None) + (args.kwarg is not None)


def _is_command(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    """A click command's callback: decorated with ``click.…`` or ``@….command``/``option``."""
    for decorator in node.decorator_list:
        text = ast.unparse(decorator)
        if text.startswith("click.") or re.search(r"(^|\.)(command|group|option|argument)\b", text):
            return True
    return False


def public_functions(tree: ast.Module):
    """Every public function and method of a module: (node, dotted name); a name starting
    with ``_``, a function nested in another and the members of a private class are not,
    but a public class's ``__init__`` is (it is how the class is called)."""

    def visit(body, prefix):
        for node in body:
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                if not node.name.startswith("_") or (prefix and node.name == "__init__"):
                    yield node, prefix + node.name
            elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
                yield from visit(node.body, f"{prefix}{node.name}.")
            elif isinstance(node, ast.If | ast.Try):  # definitions under a guard
                for block in (node.body, node.orelse, getattr(node, "finalbody", [])):
                    yield from visit(block, prefix)

    yield from visit(tree.body, "")


def test_no_public_function_takes_more_than_12_parameters():
    long = []
    for path in _python_files(PACKAGE):
        for node, name in public_functions(ast.parse(path.read_text(encoding="utf-8"))):
            n = parameter_count(node)
            if n > MAX_PARAMETERS and not _is_command(node):
                long.append(f"{_where(path, node.lineno)} {name}: {n} parameters")
    assert not long, "group what belongs together into a parameter object:\n" + "\n".join(long)


def test_the_parameter_rule_counts_what_it_should():
    tree = ast.parse(
        "class A:\n"
        "    def __init__(self, a): pass\n"
        "    def m(self, a, /, b, *c, d, **e): pass\n"
        "    def _hidden(self, *a): pass\n"
        "@cli.command()\n@click.option('--x')\ndef run(x): pass\n"
        "def outer(p):\n    def inner(q): pass\n"
        "class _Private:\n    def m(self): pass\n"
    )
    found = {name: node for node, name in public_functions(tree)}
    assert set(found) == {"A.__init__", "A.m", "run", "outer"}
    assert parameter_count(found["A.m"]) == 5 and parameter_count(found["outer"]) == 1
    assert _is_command(found["run"]) and not _is_command(found["A.m"])


def test_every_public_function_method_and_class_has_a_docstring():
    missing = []

    def visit(body, path, prefix):
        for node in body:
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                if node.name.startswith("_"):
                    continue
                if ast.get_docstring(node) is None:
                    missing.append(f"{_where(path, node.lineno)} {prefix}{node.name}")
                if isinstance(node, ast.ClassDef):
                    visit(node.body, path, f"{prefix}{node.name}.")

    for path in _python_files(PACKAGE):
        visit(ast.parse(path.read_text(encoding="utf-8")).body, path, "")
    assert not missing, "no docstring:\n" + "\n".join(missing)


def test_nothing_points_outside_the_repository():
    found = [
        _where(path, n)
        for path in _text_files()
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if OUTSIDE.search(line)
    ]
    assert not found, "cite docs/reference/model.md as 'model reference §N':\n" + "\n".join(found)


def test_no_issue_numbers_finding_codes_agents_or_helpers():
    found = []
    for path in _text_files():
        if path.parts[-2:] == ("tests", "test_docs.py"):
            continue  # names the words it forbids in the docs
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            for what, pattern in (
                ("an issue number", ISSUE),
                ("a finding code", FINDING),
                ("a test named by a code", CODE_NAME),
                ("a word of the work, not of the product", WORK_WORDS),
            ):
                if pattern.search(line):
                    found.append(f"{_where(path, n)}: {what}")
    assert not found, "\n".join(found)


def test_session_only_in_its_technical_meanings():
    found = [
        _where(path, n)
        for path in _python_files(PACKAGE, TESTS)
        if str(path.relative_to(ROOT)) not in SESSION_FILES
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if SESSION.search(line)
    ]
    assert not found, "\n".join(found)


def _comments_and_docstrings(text: str):
    """(line, text) of every comment and every triple-quoted string of Python source."""
    for token in tokenize.generate_tokens(io.StringIO(text).readline):
        if token.type == tokenize.COMMENT:
            yield token.start[0], token.string
        elif token.type == tokenize.STRING and token.string.lstrip("rbuRBU").startswith(
            ('"""', "'''")
        ):
            yield token.start[0], token.string


def test_no_dates_of_work_in_comments_and_docstrings():
    found = []
    for path in _python_files(PACKAGE, TESTS):
        for line, text in _comments_and_docstrings(path.read_text(encoding="utf-8")):
            if DATE.search(text):
                found.append(_where(path, line))
    for path in sorted(PACKAGE.rglob("*.toml")):
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if line.lstrip().startswith("#") and DATE.search(line):
                found.append(_where(path, n))
    assert not found, "dates belong to git and CHANGELOG.md:\n" + "\n".join(found)


def test_the_checks_see_what_they_forbid():
    assert OUTSIDE.search(_NOTE + " §3") and OUTSIDE.search("../shared/x")
    assert ISSUE.search("iss" + "ue 12") and FINDING.search("find" + "ings S3/S4")
    assert CODE_NAME.search("def test_" + "S5_x():") and WORK_WORDS.search("hel" + "per")
    assert DATE.search("set 2026-11-25") and not ISSUE.search("tissue 3")
