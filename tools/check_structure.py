#!/usr/bin/env python3
"""Checks the code's shape (issue 23's limits), so that it stays as the review left it.

- no source file over 1,200 lines (src/, python/src/);
- no import cycle between the library's top-level modules: an edge A -> B for every
  `crate::B` that a file of A names outside its tests;
- `main.rs` under 400 lines.

Functions over 150 lines are caught by clippy's `too_many_lines` (clippy.toml), run by CI.
Exits 1 with one line per breach.
"""
import os
import re
import sys

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
MAX_FILE_LINES = 1200
MAX_MAIN_LINES = 400


def rust_files(top):
    for dirpath, _, names in os.walk(os.path.join(ROOT, top)):
        for n in sorted(names):
            if n.endswith(".rs"):
                yield os.path.join(dirpath, n)


def without_tests(text):
    """The text before a file's `#[cfg(test)] mod ... {` block (tests come last here)."""
    m = re.search(r"#\[cfg\(test\)\]\s*mod\s+\w+\s*\{", text)
    return text[: m.start()] if m else text


def top_module(path):
    rel = os.path.relpath(path, os.path.join(ROOT, "src"))
    first = rel.split(os.sep)[0]
    return first[:-3] if first.endswith(".rs") else first


def cycles(graph):
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(10000)
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def main():
    problems = []
    for top in ("src", "python/src"):
        for path in rust_files(top):
            n = sum(1 for _ in open(path, encoding="utf-8"))
            rel = os.path.relpath(path, ROOT)
            if n > MAX_FILE_LINES:
                problems.append(f"{rel}: {n} lines (at most {MAX_FILE_LINES})")
            if rel == os.path.join("src", "main.rs") and n >= MAX_MAIN_LINES:
                problems.append(f"{rel}: {n} lines (under {MAX_MAIN_LINES})")

    graph = {}
    for path in rust_files("src"):
        if path.endswith(os.path.join("src", "main.rs")) or os.sep + "tests" in path[len(ROOT):]:
            continue
        if re.search(r"(^|/)(tests|timing_tests)\.rs$", path):
            continue
        a = top_module(path)
        text = without_tests(open(path, encoding="utf-8").read())
        text = re.sub(r"//[^\n]*", "", text)  # comments and docs name modules too
        deps = graph.setdefault(a, set())
        for b in re.findall(r"\bcrate::(\w+)", text):
            if b != a:
                deps.add(b)
        # `use crate::{a, b::c}` groups
        for group in re.findall(r"\bcrate::\{([^}]*)\}", text):
            for b in re.findall(r"(?:^|,)\s*(\w+)", group):
                if b != a:
                    deps.add(b)
    for comp in cycles(graph):
        problems.append("import cycle between top-level modules: " + " <-> ".join(comp))

    for p in problems:
        print(f"structure: {p}")
    if problems:
        return 1
    print(f"structure: ok ({len(graph)} top-level modules, no cycle, no file over {MAX_FILE_LINES} lines)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
