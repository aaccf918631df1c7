"""The user docs hold what they promise: the README is short and its pictures and links exist,
no product page names an issue number, and docs/results.md is what scripts/results.py makes of
the benchmark's JSON (a hand edit or a new bench run without regenerating fails here)."""

from __future__ import annotations

import ast
import importlib.util
import inspect
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PRODUCT_DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def _results_module():
    spec = importlib.util.spec_from_file_location("results", REPO / "scripts" / "results.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_readme_is_short():
    n = len((REPO / "README.md").read_text().splitlines())
    assert n < 200, f"README.md has {n} lines"


def test_links_and_pictures_exist():
    link = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
    for page in PRODUCT_DOCS:
        for target in link.findall(page.read_text()):
            if "://" in target:
                continue
            assert (page.parent / target).exists(), f"{page.name} links to missing {target}"


def test_no_issue_numbers_in_product_docs():
    pat = re.compile(r"\bissues? #?\d+|#\d{1,4}\b", re.I)
    for page in PRODUCT_DOCS:
        for i, line in enumerate(page.read_text().splitlines(), 1):
            assert not pat.search(line), f"{page.name}:{i}: {line.strip()}"


def test_results_page_is_generated_from_the_bench_json():
    mod = _results_module()
    assert (REPO / "docs" / "results.md").read_text() == mod.render(), (
        "docs/results.md is stale: run python scripts/results.py"
    )


def test_results_page_follows_the_json(tmp_path):
    """The generator reads the figures from the JSON (a changed number changes the page) and
    leaves out what a run did not write."""
    import json
    import shutil

    mod = _results_module()
    src = REPO / "docs" / "bench" / "accuracy.json"
    acc = json.loads(src.read_text())
    row = next(r for r in acc["rows"] if r["name"] == "cfsr" and not r["scene"].startswith("reds"))
    row["psnr_all"] = 99.125
    (tmp_path / "accuracy.json").write_text(json.dumps(acc))
    page = mod.render(tmp_path)
    assert "**99.12 / " in page
    assert "## Throughput" not in page and "## Cost follows the scene" not in page
    shutil.copy(REPO / "docs" / "bench" / "sweep.json", tmp_path / "sweep.json")
    assert "## Cost follows the scene" in mod.render(tmp_path)


# -- the README's Python: its examples run and its signatures are the real ones -------------
def _readme() -> str:
    return (REPO / "README.md").read_text()


def _fenced(text: str, lang: str) -> list[str]:
    return re.findall(rf"^```{lang}\n(.*?)^```", text, re.M | re.S)


def test_readme_python_examples_run_and_say_what_they_return(tmp_path, monkeypatch):
    """Each ```python block runs, in a folder where the tour's ``cfsr simulate`` line made the
    recording it reads; a comment ``# DTYPE (SHAPE)`` or ``# DTYPE ...`` on an assignment is
    checked against the value assigned."""
    from cfsr.cli import main

    text = _readme()
    blocks = _fenced(text, "python")
    assert blocks, "the README has no Python example"
    sim = next(line.split("#")[0].split()[1:] for block in _fenced(text, "sh")
               for line in block.splitlines() if line.startswith("cfsr simulate "))
    monkeypatch.chdir(tmp_path)
    assert main(sim) == 0
    claim = re.compile(r"^(\w+) = .*#\s*(float32|float64|uint8|bool)\b\s*(\(([\d, ]+)\))?")
    checked = 0
    for block in blocks:
        ns: dict = {}
        exec(compile(block, "README.md", "exec"), ns)  # noqa: S102 - the README's own code
        for line in block.splitlines():
            m = claim.match(line)
            if m:
                value = ns[m.group(1)]
                assert str(value.dtype) == m.group(2), line
                if m.group(4):
                    shape = tuple(int(x) for x in m.group(4).split(","))
                    assert value.shape == shape, (line, value.shape)
                checked += 1
    assert checked >= 2


def _documented_calls(text: str) -> list[tuple[str, str]]:
    """(``cfsr.NAME``, its argument list) for each ``cfsr.NAME(ARGS)`` code span of ``text``
    (a span may wrap onto the next line)."""
    return [(name, " ".join(args.split()))
            for name, args in re.findall(r"`(cfsr\.[A-Za-z_]+)\(([^`)]*)\)`", text)]


def _params(args: str) -> list[tuple[str, str, object]]:
    """(name, kind, default) of a documented argument list; ``...`` as a default: elided."""
    node = ast.parse(f"def f({args}): pass").body[0].args
    out = []
    pos = [*node.posonlyargs, *node.args]
    pos_defaults = [None] * (len(pos) - len(node.defaults)) + list(node.defaults)
    for a, d in zip(pos, pos_defaults, strict=True):
        out.append((a.arg, "POSITIONAL_OR_KEYWORD", d))
    if node.vararg:
        out.append((node.vararg.arg, "VAR_POSITIONAL", None))
    for a, d in zip(node.kwonlyargs, node.kw_defaults, strict=True):
        out.append((a.arg, "KEYWORD_ONLY", d))
    if node.kwarg:
        out.append((node.kwarg.arg, "VAR_KEYWORD", None))
    return [(n, k, inspect.Parameter.empty if d is None else ast.literal_eval(d))
            for n, k, d in out]


def test_readme_api_signatures_are_the_real_ones():
    """The contract's ``cfsr.NAME(ARGS)``: every parameter in order, of the same kind, with
    the real default (the README's ``read_dat`` once showed defaults it did not have and left
    out ``rate_hz``)."""
    import cfsr

    calls = _documented_calls(_readme())
    assert {"cfsr.read_dat", "cfsr.reconstruct", "cfsr.write_dat"} <= {c for c, _ in calls}
    wrong = []
    for name, args in calls:
        obj = getattr(cfsr, name.split(".", 1)[1])
        real = [(p.name, p.kind.name, p.default)
                for p in inspect.signature(obj).parameters.values()]
        doc = _params(args)
        if doc != real:
            wrong.append(f"{name}({args})\n  real: {inspect.signature(obj)}")
    assert not wrong, "README signatures that are not the code's:\n" + "\n".join(wrong)


# -- command-line flags named in the docs exist --------------------------------------------
#: flags the docs name that no parser has, on purpose
EXAMPLE_FLAGS = {"--mycam"}  # docs/extending.md: the flag of the source kind a reader adds
PRODUCT_SOURCES = [p for d in ("cfsr", "service", "driver", "replay", "shm")
                   for p in sorted((REPO / d).rglob("*.py"))]


def _cli_options() -> dict[str, set[str]]:
    """Each ``cfsr`` command's option strings, from the CLI's own parser."""
    import argparse

    from cfsr.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return {name: {o for a in sp._actions for o in a.option_strings}
            for name, sp in sub.choices.items()}


def _code_snippets(text: str) -> list[str]:
    """Lines of fenced blocks and inline code spans (where the docs write commands)."""
    out, fenced = [], False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif fenced:
            out.append(line)
        else:
            out.extend(re.findall(r"`+([^`\n]+)`+", line))
    return out


def _named_flags(snippet: str) -> list[tuple[str, str]]:
    """(command, flag) for each ``--flag`` that follows ``cfsr COMMAND`` in a snippet."""
    out = []
    parts = re.split(r"\bcfsr ([a-z]+)\b", snippet)
    for cmd, rest in zip(parts[1::2], parts[2::2], strict=True):
        out.extend((cmd, f) for f in re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", rest))
    return out


def test_cli_flags_named_in_the_docs_exist():
    """Every ``cfsr COMMAND --flag`` in the README, docs/*.md and the product's docstrings is
    an option of that command's parser."""
    options = _cli_options()
    named, wrong = 0, []
    for path in [*PRODUCT_DOCS, *PRODUCT_SOURCES]:
        for snippet in _code_snippets(path.read_text()):
            for cmd, flag in _named_flags(snippet):
                named += 1
                if cmd not in options:
                    wrong.append(f"{path.relative_to(REPO)}: no command 'cfsr {cmd}'")
                elif flag not in options[cmd] and flag not in EXAMPLE_FLAGS:
                    wrong.append(f"{path.relative_to(REPO)}: 'cfsr {cmd}' has no {flag}")
    assert named > 50
    assert not wrong, "\n".join(wrong)


def test_the_flag_check_reads_commands_as_the_docs_write_them():
    assert _named_flags("cfsr serve --replay x.dat   # or --usb; then cfsr info --json") == [
        ("serve", "--replay"), ("serve", "--usb"), ("info", "--json")]
    assert _code_snippets("a `cfsr b --c` and ``cfsr d --e``\n```sh\ncfsr f --g\n```\n") == [
        "cfsr b --c", "cfsr d --e", "cfsr f --g"]


def _install_table() -> dict[str, list[str]]:
    """The README's install table: extra ("" for the base install) -> the commands it lists."""
    out = {}
    for line in _readme().splitlines():
        m = re.match(r"\| `cfsr(?:\[(\w+)\])?` \|[^|]*\|(.*)\|$", line)
        if m:
            out[m.group(1) or ""] = re.findall(r"`([^`]+)`", m.group(2))
    return out


def test_commands_listed_under_an_extra_are_the_readmes():
    """The CLI lists a command under an extra (shown as unavailable without it) only where the
    README's install table does, and never one the base install runs (``record --replay``)."""
    from cfsr.cli import EXTRA_COMMANDS
    from cfsr.cli._extras import EXTRAS

    table = _install_table()
    assert {"", "live", "cluster", "bench"} <= set(table), table
    base = {c.split()[0] for c in table[""]}
    assert "record" in base
    for name, (extra, _) in EXTRA_COMMANDS.items():
        assert name not in base, f"'cfsr {name}' runs on the base install, yet is listed [{extra}]"
        assert name in table[extra], f"'cfsr {name}' is not in the README's cfsr[{extra}] row"
    for extra, (what, _) in EXTRAS.items():
        for cmd in re.findall(r"cfsr ([a-z]+)\b(?! --)", what):
            assert cmd not in base, f"cfsr[{extra}] claims 'cfsr {cmd}', a base command"
