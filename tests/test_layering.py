"""The shape of the code base, checked on its import statements (an AST walk; import-linter is not installed).

Rules:

1. ``toolkit`` never imports ``export`` or ``viewers`` — except ``toolkit/cli/``, the command line. Every import
   counts: module level, inside functions, under ``if TYPE_CHECKING:``.
2. ``export`` never imports ``viewers`` (every import counts, as in 1).
3. No import cycle among the modules of ``toolkit``, ``export`` and ``viewers``. Imports inside functions count too
   (a lazy import hides a cycle from Python, not from the reader: the three cycles issue 15 removed —
   field → train → pipeline → field, ``_cli_light`` ↔ ``_cli_priors``, ``viewers/preview`` ↔ ``shading_glsl`` —
   were all function-local); only ``if TYPE_CHECKING:`` blocks, which never run, are left out. Importing ``a.b.c`` also runs the
   packages ``a`` and ``a.b``, so it counts as importing them too — except for the importing module's own parent
   packages (a package importing its submodules is not a cycle).

And ``dars --help`` / ``dars COMMAND --help`` load no heavy module (torch, numpy, Open3D, ...): the command modules
import those inside their handlers.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("toolkit", "export", "viewers")
HEAVY = ("torch", "numpy", "scipy", "open3d", "cv2", "onnxruntime", "onnx", "kornia", "matplotlib", "moderngl",
         "pymeshlab", "trimesh", "xatlas", "skimage", "PIL", "tqdm")


@dataclass(frozen=True)
class Import:
    source: str
    """Importing module, e.g. ``toolkit.cli.view``."""
    target: str
    """Imported module (or package), e.g. ``viewers.camera``."""
    runtime: bool
    """Runs at some point (not under ``if TYPE_CHECKING:``); function-local imports included."""
    line: int


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def scan_imports(root: Path, packages: tuple[str, ...] = PACKAGES) -> tuple[set[str], list[Import]]:
    """(every module, every import between them) of the packages under ``root``."""
    files = {module_name(p, root): p for pkg in packages for p in sorted((root / pkg).rglob("*.py"))}
    modules = set(files)
    found: list[Import] = []
    for mod, path in files.items():
        is_pkg = path.name == "__init__.py"
        package = mod if is_pkg else mod.rpartition(".")[0]

        def resolve(node: ast.ImportFrom) -> str:
            if not node.level:
                return node.module or ""
            base = package.split(".")
            base = base[:len(base) - node.level + 1]
            return ".".join(base + ([node.module] if node.module else []))

        def visit(node: ast.AST, runtime: bool) -> None:
            for child in ast.iter_child_nodes(node):
                type_checking = isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test)
                child_runtime = runtime and not type_checking
                if isinstance(child, ast.Import):
                    for alias in child.names:
                        found.append(Import(mod, alias.name, runtime, child.lineno))
                elif isinstance(child, ast.ImportFrom):
                    target = resolve(child)
                    for alias in child.names:  # `from pkg import submodule` imports the submodule
                        sub = f"{target}.{alias.name}"
                        found.append(Import(mod, sub if sub in modules else target, runtime, child.lineno))
                visit(child, child_runtime)

        visit(ast.parse(path.read_text(), str(path)), True)
    return modules, [i for i in found if i.target.split(".")[0] in packages]


def layering_violations(imports: list[Import]) -> list[str]:
    """Rules 1 and 2 (every import, wherever it is)."""
    bad = []
    for i in imports:
        src, dst = i.source.split(".")[0], i.target.split(".")[0]
        cli = i.source == "toolkit.cli" or i.source.startswith("toolkit.cli.")
        if src == "toolkit" and dst in ("export", "viewers") and not cli:
            bad.append(f"{i.source}:{i.line} imports {i.target} (only toolkit/cli/ may import export/ and viewers/)")
        if src == "export" and dst == "viewers":
            bad.append(f"{i.source}:{i.line} imports {i.target} (export/ must not import viewers/)")
    return bad


def import_graph(modules: set[str], imports: list[Import]) -> dict[str, set[str]]:
    """Import edges of rule 3 (every import that runs), with the packages an import runs."""
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for i in imports:
        if not i.runtime:
            continue
        own_parents = {i.source.rsplit(".", k)[0] for k in range(1, i.source.count(".") + 1)}
        parts = i.target.split(".")
        for n in range(1, len(parts) + 1):
            t = ".".join(parts[:n])
            if t in modules and t != i.source and (t == i.target or t not in own_parents):
                graph[i.source].add(t)
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []
    counter = [0]

    def strong(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    return cycles


# ------------------------------------------------------------------------------------------------------------ the rules
def test_toolkit_never_imports_export_or_viewers_and_export_never_imports_viewers():
    _, imports = scan_imports(ROOT)
    assert any(i.source.startswith("toolkit.cli.") and i.target.startswith("viewers") for i in imports)  # scan works
    assert layering_violations(imports) == []


def test_no_import_cycles():
    modules, imports = scan_imports(ROOT)
    assert {"toolkit.train", "toolkit.train.run", "toolkit.mesh.extract", "export.infer", "viewers.gl"} <= modules
    assert import_cycles(import_graph(modules, imports)) == []


def test_the_checks_catch_a_bad_import_and_a_cycle(tmp_path):
    """A synthetic tree: each rule must fire on the import that breaks it."""
    files = {
        "toolkit/__init__.py": "",
        "toolkit/a.py": "from . import b\n",
        "toolkit/b.py": "import toolkit.a\n\n\ndef f():\n    from export import x  # a function-local import counts\n",
        "toolkit/c.py": "def g():\n    from .d import y  # function-local: still a cycle\n",
        "toolkit/d.py": "from .c import g\n",
        "toolkit/e.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .f import z\n",
        "toolkit/f.py": "from .e import w\n",
        "toolkit/pkg/__init__.py": "from .m import q\n",
        "toolkit/pkg/m.py": "from . import n\n",
        "toolkit/pkg/n.py": "",
        "toolkit/cli/__init__.py": "import viewers.v\n",
        "export/__init__.py": "",
        "export/x.py": "from viewers.v import thing\n",
        "viewers/__init__.py": "",
        "viewers/v.py": "from export.x import other\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    modules, imports = scan_imports(tmp_path)
    bad = layering_violations(imports)
    assert len(bad) == 2, bad
    assert "toolkit.b:5 imports export" in bad[0] or "toolkit.b:5 imports export" in bad[1]
    assert any(b.startswith("export.x:1 imports viewers.v") for b in bad)
    cycles = import_cycles(import_graph(modules, imports))
    assert sorted(cycles) == [["export.x", "viewers.v"], ["toolkit.a", "toolkit.b"], ["toolkit.c", "toolkit.d"]], cycles


# ------------------------------------------------------------------------------------------------------------ --help
def test_help_imports_no_heavy_module():
    """``dars --help`` under ``-X importtime``: no torch; every ``dars COMMAND --help`` page: no heavy module."""
    r = subprocess.run([sys.executable, "-X", "importtime", "-m", "toolkit.cli", "--help"], capture_output=True,
                       text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0 and "export-asset" in r.stdout, r.stderr[-2000:]
    loaded = {line.rsplit("|", 1)[-1].strip() for line in r.stderr.splitlines() if line.startswith("import time:")}
    assert "toolkit.cli" in loaded  # the timing lines were read
    assert not [m for m in loaded if m.split(".")[0] in HEAVY], sorted(m for m in loaded if m.split(".")[0] in HEAVY)
    code = ("import json, sys\nfrom toolkit.cli import build_parser\np = build_parser()\n"
            "sub = next(a for a in p._actions if a.dest == 'command')\n"
            "pages = [p.format_help()] + [q.format_help() for q in sub.choices.values()]\n"
            "stages = sub.choices['priors']._actions[-1].choices\n"
            "pages += [q.format_help() for q in stages.values()]\n"
            f"print(json.dumps({{'pages': len(pages), 'heavy': sorted(m for m in sys.modules "
            f"if m.split('.')[0] in {HEAVY!r})}}))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["pages"] > 20 and d["heavy"] == [], d
