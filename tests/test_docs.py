"""The docs say what the code does: the REST reference is the app's OpenAPI document as
scripts/gen_rest_docs.py renders it, every `crowdbake` command in a page's `sh` blocks parses with the
real command line, and every link and figure in docs/ points at a file that exists."""
from __future__ import annotations

import importlib.util
import re
import shlex
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
DOCS = REPO_ROOT / "docs"
sys.path.insert(0, str(REPO_ROOT / "services"))


def load_script(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO_ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def code_blocks(text: str, language: str = "sh") -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", text, flags=re.DOTALL)


def commands(block: str) -> list[str]:
    """Shell commands of a block: continuation lines joined, comments and blank lines dropped."""
    joined = re.sub(r"\\\n\s*", " ", block)
    return [line.split(" #")[0].strip() for line in joined.splitlines() if line.strip() and not line.lstrip().startswith("#")]


def test_rest_reference_is_the_apps_openapi_document():
    generator = load_script("gen_rest_docs")
    expected = generator.render(generator.openapi_document())
    committed = (DOCS / "rest-api.md").read_text(encoding="utf-8")
    assert committed == expected, "docs/rest-api.md is out of date: run .venv/bin/python scripts/gen_rest_docs.py"


def test_rest_reference_lists_every_operation():
    generator = load_script("gen_rest_docs")
    document = generator.openapi_document()
    text = (DOCS / "rest-api.md").read_text(encoding="utf-8")
    for path, item in document["paths"].items():
        for method in generator.METHODS:
            if method in item:
                assert f"### `{method.upper()} {path}`" in text


def crowdbake_arguments(page: Path) -> list[list[str]]:
    """The arguments of every `crowdbake` command (the command's first word) in the page's `sh` blocks."""
    found = []
    for block in code_blocks(page.read_text(encoding="utf-8")):
        for command in commands(block):
            words = shlex.split(command.split("|")[0].split(" > ")[0].split(" &")[0])
            if words and Path(words[0]).name == "crowdbake" and words[1:2] not in (["--version"], ["--help"]):
                found.append(words[1:])
    return found


def test_quickstart_crowdbake_commands_parse_with_the_real_command_line():
    from crowdbake.cli import build_parser

    parser = build_parser()
    checked = 0
    for words in crowdbake_arguments(DOCS / "quickstart.md"):
        try:
            args = parser.parse_args(words)
        except SystemExit:
            pytest.fail(f"quickstart command does not parse: crowdbake {' '.join(words)}")
        assert getattr(args, "func", None), words
        checked += 1
    assert checked >= 5  # sample, cycle, bake, keys, serve, submit at least


@pytest.mark.parametrize("page", sorted(DOCS.glob("*.md")) + [REPO_ROOT / "runtime" / "README.md"], ids=lambda page: page.name)
def test_every_crowdbake_command_in_the_docs_parses(page):
    """bake.md's several-clips example once lacked --name/--version/--out and stopped with a usage error:
    every command a reader may paste from an `sh` block must parse with the real command line."""
    from crowdbake.cli import build_parser

    parser = build_parser()
    for words in crowdbake_arguments(page):
        try:
            parser.parse_args(words)
        except SystemExit:
            pytest.fail(f"{page.name}: command does not parse: crowdbake {' '.join(words)}")


def test_the_command_check_sees_a_command_that_does_not_parse(tmp_path):
    from crowdbake.cli import build_parser

    page = tmp_path / "page.md"
    page.write_text("```sh\ncrowdbake bake robot.glb --cloth g.pc2 --cloth-mesh g.obj \\\n    --frames 2\n```\n", encoding="utf-8")
    assert crowdbake_arguments(page) == [["bake", "robot.glb", "--cloth", "g.pc2", "--cloth-mesh", "g.obj", "--frames", "2"]]
    with pytest.raises(SystemExit):
        build_parser().parse_args(crowdbake_arguments(page)[0])


def test_quickstart_scripts_and_programs_exist():
    text = (DOCS / "quickstart.md").read_text(encoding="utf-8")
    for script in set(re.findall(r"(?:\./)?(scripts/[\w.-]+\.(?:sh|py))", text)):
        assert (REPO_ROOT / script).is_file(), script
    for benchmark in set(re.findall(r"(services/benchmarks/[\w.-]+\.py)", (DOCS / "figures.md").read_text(encoding="utf-8"))):
        assert (REPO_ROOT / benchmark).is_file(), benchmark


@pytest.mark.parametrize("name", ["quickstart.md", "rest-api.md", "figures.md"])
def test_relative_links_and_images_resolve(name):
    text = (DOCS / name).read_text(encoding="utf-8")
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    for target in targets:
        if re.match(r"^[a-z]+://", target):
            continue
        assert (DOCS / target).resolve().exists(), f"{name} links to {target}, which does not exist"


def test_every_figure_in_docs_img_is_shown_and_every_shown_figure_exists():
    shown_in = {path.name: set(re.findall(r"!\[[^\]]*\]\((img/[^)]+\.png)\)", path.read_text(encoding="utf-8"))) for path in DOCS.glob("*.md")}
    assert shown_in.get("figures.md"), "figures.md shows no figure"
    shown = set().union(*shown_in.values())
    on_disk = {f"img/{path.name}" for path in (DOCS / "img").glob("*.png")}
    assert shown <= on_disk, shown - on_disk
    assert on_disk <= shown, f"figures in docs/img that no page shows: {sorted(on_disk - shown)}"
