"""The runtime stays a set of small flat files of short functions (STYLE.md, "few flat files, one job
each"): every C++ source in runtime/src holds at most 600 lines, and every function body, from its
opening brace to its closing one, spans at most 80 lines.

Functions are found by a brace-matching scan, not a compiler: comments, string and character literals
and preprocessor lines are blanked first, then each `{` at namespace or class scope is classified by
the text before it. A `(` there makes it a function (free, member, constructor, operator); `namespace`,
`extern` and `class`/`struct`/`union` open a scope that is scanned in turn; anything else (an enum, an
aggregate or brace initialiser) is data and skipped whole. Lambdas and local classes count towards the
function that holds them. Run this file as a script to print the largest files and longest functions.
"""
from __future__ import annotations

import re
import sys
from dataclasses import dataclass
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
SOURCE_DIR = REPO_ROOT / "runtime" / "src"
MAX_FILE_LINES = 600
MAX_FUNCTION_LINES = 80

SCOPE_KEYWORDS = re.compile(r"^\s*(?:inline\s+)?(namespace|extern)\b")
CLASS_KEYWORDS = re.compile(r"\b(class|struct|union)\b")
ENUM_KEYWORD = re.compile(r"\benum\b")
ACCESS_LABEL = re.compile(r"\b(public|private|protected)\s*:(?!:)")
OPERATOR_NAME = re.compile(r"\boperator\s*(\(\)|[^\s(]+)")
RAW_STRING = re.compile(r'(?<![\w])R"([^(\s]*)\(')
OPERATOR_FUNCTION = re.compile(r"((?:\w+(?:<[^<>]*>)?\s*::\s*)*operator\s*(?:\(\)|[^\s(]+))")
NAME_BEFORE_PAREN = re.compile(r"((?:[A-Za-z_]\w*(?:<[^<>]*>)?\s*::\s*)*~?[A-Za-z_]\w*)\s*$")
# `) :` then a single colon: a constructor's member initialiser list (`) -> std::string` has two).
INITIALISER_LIST = re.compile(r"\)[^()]*?(?<!:):(?!:)")


@dataclass(frozen=True)
class Function:
    name: str
    first_line: int  # the line of the opening brace, counted from 1
    last_line: int  # the line of the closing brace

    @property
    def lines(self) -> int:
        return self.last_line - self.first_line + 1


def blank_non_code(source: str) -> str:
    """`source` with comments, literals and preprocessor lines replaced by spaces; newlines kept, so
    offsets and line numbers still match the file."""
    out = list(source)
    i, n = 0, len(source)
    at_line_start = True

    def blank(start: int, end: int) -> None:
        for k in range(start, end):
            if out[k] != "\n":
                out[k] = " "

    while i < n:
        c = source[i]
        if c == "\n":
            at_line_start = True
            i += 1
            continue
        if c in " \t":
            i += 1
            continue
        if at_line_start and c == "#":  # a directive, with its backslash continuations
            end = i
            while end < n and (source[end] != "\n" or source[end - 1] == "\\"):
                end += 1
            blank(i, end)
            i = end
            continue
        at_line_start = False
        if source.startswith("//", i):
            end = source.find("\n", i)
            end = n if end < 0 else end
            blank(i, end)
            i = end
        elif source.startswith("/*", i):
            end = source.find("*/", i + 2)
            end = n if end < 0 else end + 2
            blank(i, end)
            i = end
        elif raw := RAW_STRING.match(source, i):
            end = source.find(")" + raw.group(1) + '"', i)
            end = n if end < 0 else end + len(raw.group(1)) + 2
            blank(i + 1, end - 1)
            i = end
        elif c == '"' or (c == "'" and not (i > 0 and source[i - 1].isalnum())):
            end = i + 1
            while end < n and source[end] != c and source[end] != "\n":
                end += 2 if source[end] == "\\" else 1
            blank(i + 1, end)
            i = end + 1
        else:
            i += 1
    return "".join(out)


def matching_brace(code: str, open_at: int) -> int:
    """The offset of the `}` that closes the `{` at `open_at` (len(code) when it is never closed)."""
    depth = 0
    for k in range(open_at, len(code)):
        if code[k] == "{":
            depth += 1
        elif code[k] == "}":
            depth -= 1
            if depth == 0:
                return k
    return len(code)


def strip_templates(header: str) -> str:
    """`header` without its leading `template <...>` clauses."""
    while (match := re.match(r"\s*template\s*<", header)) is not None:
        depth, k = 1, match.end()
        while k < len(header) and depth:
            depth += {"<": 1, ">": -1}.get(header[k], 0)
            k += 1
        header = header[k:]
    return header


def top_level(text: str) -> str:
    """`text` with everything inside parentheses blanked: what a declaration says outside its
    parameter lists."""
    out, depth = [], 0
    for c in text:
        if c == ")":
            depth -= 1
        out.append(c if depth == 0 else " ")
        if c == "(":
            depth += 1
    return "".join(out)


def classify(header: str) -> str:
    """What the `{` after `header` opens at namespace or class scope: "scope", "class", "function",
    "initializer" (a constructor's member initialiser such as `y_{b}`, the body comes later) or "data"."""
    header = strip_templates(ACCESS_LABEL.sub(" ", header))
    outside = top_level(OPERATOR_NAME.sub("operator_", header))
    if SCOPE_KEYWORDS.match(header) and "(" not in outside:
        return "scope"
    if "=" in outside or ENUM_KEYWORD.search(outside):
        return "data"
    if "(" not in outside:
        return "class" if CLASS_KEYWORDS.search(outside) else "data"
    if INITIALISER_LIST.search(outside) and re.search(r"[\w>]\s*$", header):
        return "initializer"
    return "function"


def function_name(header: str) -> str:
    """The (qualified) name a function definition's `header` declares: the word before its first
    parameter list, or the operator it defines."""
    header = strip_templates(ACCESS_LABEL.sub(" ", header))
    match = OPERATOR_FUNCTION.search(header)
    if match is None:
        match = NAME_BEFORE_PAREN.search(header[: header.find("(")])
    return re.sub(r"\s+", "", match.group(1)) if match else header.strip()


def find_functions(source: str) -> list[Function]:
    """Every function defined at namespace or class scope in `source`, with the lines its body spans."""
    code = blank_non_code(source)
    line_of = [0] * (len(code) + 1)
    for k, c in enumerate(code):
        line_of[k + 1] = line_of[k] + (c == "\n")
    functions: list[Function] = []

    def scan(start: int, end: int) -> None:
        header_start, k = start, start
        while k < end:
            c = code[k]
            if c in ";}":
                header_start = k + 1
            elif c == "{":
                close = matching_brace(code, k)
                header = code[header_start:k]
                kind = classify(header)
                if kind in ("scope", "class"):
                    scan(k + 1, close)
                elif kind == "function":
                    functions.append(Function(function_name(header), line_of[k] + 1, line_of[close] + 1))
                if kind != "initializer":
                    header_start = close + 1
                k = close
            k += 1

    scan(0, len(code))
    return functions


def runtime_sources() -> list[Path]:
    return sorted(p for p in SOURCE_DIR.rglob("*") if p.suffix in (".cpp", ".h", ".hpp"))


def line_count(path: Path) -> int:
    return len(path.read_text(encoding="utf-8").splitlines())


# ---------------------------------------------------------------------------------------------
# The runtime's own sources


def test_the_runtime_sources_are_found():
    names = {p.name for p in runtime_sources()}
    assert {"main.cpp", "crowd.h", "bundle.cpp"} <= names


def test_every_runtime_file_is_at_most_600_lines():
    too_long = {str(p.relative_to(REPO_ROOT)): n for p in runtime_sources() if (n := line_count(p)) > MAX_FILE_LINES}
    assert not too_long, f"files over {MAX_FILE_LINES} lines: {too_long}"


def test_every_runtime_function_is_at_most_80_lines():
    too_long = [
        f"{p.relative_to(REPO_ROOT)}:{f.first_line} {f.name} ({f.lines} lines)"
        for p in runtime_sources()
        for f in find_functions(p.read_text(encoding="utf-8"))
        if f.lines > MAX_FUNCTION_LINES
    ]
    assert not too_long, f"functions over {MAX_FUNCTION_LINES} lines: {too_long}"


def test_the_scan_finds_the_runtime_functions_a_reader_knows():
    """The scan sees real definitions in the real files: a free function, a member function and a
    function defined inside a class body."""
    names = {
        p.name: {f.name for f in find_functions(p.read_text(encoding="utf-8"))} for p in runtime_sources()
    }
    assert "main" in names["main.cpp"]
    assert any(name.startswith("Renderer::") for name in names["renderer.cpp"])
    assert "total" in names["renderer.h"]  # ArchetypeMemory::total(), defined in its struct


# ---------------------------------------------------------------------------------------------
# The scanner on C++ whose answer is known by construction


def synthetic_source(long_body_lines: int) -> str:
    long_body = "".join(f"    total += {k};  // a {{ brace in a comment\n" for k in range(long_body_lines))
    return (
        "#include <string>\n"
        "#define BLOCK(x) { x; }\n"
        "namespace demo {\n"
        "enum class Mode { a, b };\n"
        "const int table[] = {1, 2, 3};\n"
        "struct Widget {\n"
        "    int size() const { return 3; }\n"
        "    Widget(int a) : a_(a), b_{a} {\n"
        "        a_ += 1;\n"
        "    }\n"
        "    bool operator==(const Widget& o) const { return a_ == o.a_; }\n"
        "    int a_, b_;\n"
        "};\n"
        "namespace {\n"
        "int helper(const std::string& s = \"{\") {\n"
        "    auto twice = [](int v) { return 2 * v; };\n"
        "    if (s.empty()) { return twice('}'); }\n"
        "    return 0;\n"
        "}\n"
        "}  // namespace\n"
        "int Widget_sum(int total) {\n"
        f"{long_body}"
        "    return total;\n"
        "}\n"
        "template <typename T>\n"
        "T Box<T>::get() const {\n"
        "    return value;\n"
        "}\n"
        "}  // namespace demo\n"
    )


def test_the_scan_finds_each_kind_of_definition_and_its_length():
    """Inline members, a constructor with a brace member initialiser, an operator, a function in an
    anonymous namespace holding a lambda and braces in literals, a free function, a template member;
    the enum, the aggregate and the macro are not functions."""
    functions = {f.name: f.lines for f in find_functions(synthetic_source(long_body_lines=90))}
    assert functions == {
        "size": 1,
        "Widget": 3,
        "operator==": 1,
        "helper": 5,
        "Widget_sum": 90 + 3,  # its opening line, the body, the return, the closing brace
        "Box<T>::get": 3,
    }


def test_the_function_check_fails_on_a_function_over_the_limit():
    too_long = [f.name for f in find_functions(synthetic_source(long_body_lines=90)) if f.lines > MAX_FUNCTION_LINES]
    assert too_long == ["Widget_sum"]
    short = [f.name for f in find_functions(synthetic_source(long_body_lines=10)) if f.lines > MAX_FUNCTION_LINES]
    assert short == []


def report() -> str:
    """The five largest files and the ten longest functions of runtime/src."""
    files = sorted(((line_count(p), p) for p in runtime_sources()), key=lambda item: -item[0])
    functions = sorted(
        ((f.lines, f"{p.relative_to(SOURCE_DIR)}:{f.first_line} {f.name}") for p in runtime_sources()
         for f in find_functions(p.read_text(encoding="utf-8"))),
        key=lambda item: -item[0],
    )
    lines = [f"{n:5d}  {p.relative_to(SOURCE_DIR)}" for n, p in files[:5]]
    lines += [f"{n:5d}  {where}" for n, where in functions[:10]]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.stdout.write(report() + "\n")
