"""The house's layering (DESIGN.md §2), checked on the source: contracts at the bottom, no import cycle
counting imports inside functions, drivers on contracts only, one namespace, one name per contact field."""
from __future__ import annotations

import ast
import re
import tomllib
from dataclasses import fields
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("contracts", "drivers", "runtime", "tools")


def _modules() -> dict[str, Path]:
    out = {}
    for top in PACKAGES:
        for f in (ROOT / top).rglob("*.py"):
            parts = list(f.relative_to(ROOT).with_suffix("").parts)
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f
    return out


def import_graph() -> dict[str, set[str]]:
    """Module → project modules it imports (any depth in the file, relative imports resolved)."""
    mods = _modules()
    graph = {m: set() for m in mods}
    for m, f in mods.items():
        pkg = m if f.name == "__init__.py" else m.rpartition(".")[0]
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    up = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                    base = ".".join(up + ([node.module] if node.module else []))
                else:
                    base = node.module or ""
                targets = [base] + [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            for t in targets:
                t = t.removeprefix("tensortouch.")
                while t and t not in mods:
                    t = t.rpartition(".")[0]
                if t and t != m and mods[t].name != "__init__.py":
                    graph[m].add(t)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]; counter[0] += 1; stack.append(root); on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter[0]; counter[0] += 1; stack.append(w); on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    x = stack.pop(); on.discard(x); comp.append(x)
                    if x == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_cycle_finder_finds_a_hand_made_cycle():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(g) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_at_any_level():
    graph = import_graph()
    assert sum(len(v) for v in graph.values()) > 500, "the graph lost its edges: imports are not being resolved"
    assert cycles(graph) == []


def test_contracts_at_the_bottom_and_drivers_on_contracts_only():
    graph = import_graph()
    for m, deps in graph.items():
        top = m.split(".")[0]
        tops = {d.split(".")[0] for d in deps}
        if top == "contracts":
            assert tops <= {"contracts"}, f"{m} imports {sorted(deps)}"
        if top == "drivers":
            assert tops <= {"contracts", "drivers"}, f"{m} imports {sorted(deps)}"
        if top == "runtime":
            assert "tools" not in tops, f"{m} imports {sorted(deps)}"


def test_frame_loop_stages_sit_in_one_folder():
    stages = {p.stem for p in (ROOT / "runtime" / "stages").glob("*.py")} | {"effects"}
    assert {"preprocess", "baseline", "model", "contacts", "effects", "correction"} <= stages
    pipeline = (ROOT / "runtime" / "pipeline.py").read_text()
    for stage in ("preprocess", "baseline", "model", "contacts", "effects", "correction"):
        assert f".stages.{stage}" in pipeline


def test_one_namespace_no_top_level_imports_of_our_folders():
    bad = []
    pattern = re.compile(r"^\s*(from|import)\s+(runtime|drivers|tools|contracts)\b", re.M)
    for top in PACKAGES + ("tests", "integrations"):
        for f in (ROOT / top).rglob("*.py"):
            if pattern.search(f.read_text(encoding="utf-8")):
                bad.append(str(f.relative_to(ROOT)))
    assert bad == []


def test_pyproject_installs_every_package_under_the_namespace():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(cfg["packages"])
    have = {"tensortouch." + ".".join(f.parent.relative_to(ROOT).parts)
            for top in PACKAGES for f in (ROOT / top).rglob("__init__.py")}
    assert have <= listed, sorted(have - listed)
    for pkg in listed:
        head = pkg.split(".")[1] if "." in pkg else None
        if head:
            assert cfg["package-dir"][f"tensortouch.{head}"] == head


def test_contacts_carry_the_wire_names_in_memory():
    from tensortouch.contracts.wire import CONTACT_FIELDS
    from tensortouch.runtime.stages.contacts import Cluster

    assert set(CONTACT_FIELDS) <= {f.name for f in fields(Cluster)}


def test_every_command_and_option_has_help_text():
    import argparse

    from tensortouch.runtime.shells.cli import build_parser

    parser, _ = build_parser()
    missing, commands = [], 0

    def walk(p, path):
        nonlocal commands
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sp in a.choices.items():
                    commands += 1
                    walk(sp, path + [name])
            elif not isinstance(a, argparse._HelpAction) and not a.help:
                missing.append(" ".join(path + ["/".join(a.option_strings or [a.dest])]))
    walk(parser, [])
    assert commands > 40 and missing == []
