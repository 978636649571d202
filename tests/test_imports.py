"""Imports among nostra's modules go one way: no module of nostra.policies is on an import cycle
(``nostra.policies.checkpoint`` imports ``base`` and the registry, never the reverse). Imports are
read with ``ast`` from the source, function-level (lazy) ones included: a lazy import hides a cycle
from the interpreter but is still a two-way dependency."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "nostra"


def module_files(package: Path = PACKAGE) -> dict[str, Path]:
    """Dotted module name -> source file, for every module of the package."""
    out = {}
    for path in sorted(package.rglob("*.py")):
        parts = list(path.relative_to(package.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def imported_modules(name: str, source: str, modules: set[str], is_package: bool = False) -> set[str]:
    """The modules of ``modules`` that ``source`` (the module ``name``) imports anywhere in its body:
    ``import a.b``, ``from a import b`` (b a submodule, else a itself), relative imports."""
    package = name if is_package else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([node.module] if node.module else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        else:
            continue
        for t in targets:
            while t and t not in modules:  # `import nostra.x.y` names the deepest module of ours it reaches
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


def import_graph(overrides: dict[str, str] | None = None) -> dict[str, set[str]]:
    """module -> modules it imports; ``overrides`` replaces some modules' source (for the self-check)."""
    files = module_files()
    names = set(files)
    graph = {}
    for name, path in files.items():
        source = (overrides or {}).get(name, path.read_text())
        graph[name] = imported_modules(name, source, names, path.name == "__init__.py")
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative)."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def policy_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    return [c for c in cycles(graph) if any(m == "nostra.policies" or m.startswith("nostra.policies.")
                                            for m in c)]


def test_graph_sees_the_policy_modules():
    graph = import_graph()
    assert "nostra.policies.base" in graph["nostra.policies.checkpoint"]
    assert "nostra.policies" in graph["nostra.policies.checkpoint"]  # the registry
    assert "nostra.policies.base" in graph["nostra.policies.diffusion"]
    assert "nostra.policies.checkpoint" in graph["nostra.workflows.training"]
    assert "nostra.policies.checkpoint" in graph["nostra.policies.modules"]  # write_meta: training writes through it


def test_no_import_cycle_through_nostra_policies():
    assert policy_cycles(import_graph()) == []


@pytest.mark.parametrize("line", [
    "from nostra.policies.checkpoint import load_net",
    "from .checkpoint import load_net",
    "from . import checkpoint",
    "import nostra.policies.checkpoint",
    "def from_checkpoint(path):\n    from nostra.policies.checkpoint import load_net\n    return load_net(path)",
])
def test_a_re_added_import_is_caught(line):
    """The check is real: base.py importing checkpoint.py again, at module level or lazily, is a cycle."""
    base = "nostra.policies.base"
    source = module_files()[base].read_text() + "\n" + line + "\n"
    found = policy_cycles(import_graph({base: source}))
    assert any({base, "nostra.policies.checkpoint"} <= set(c) for c in found), found


def test_checkpoint_module_imports_in_a_fresh_interpreter():
    """Imported first in a new process (importing it runs the package's __init__, the registry, then
    base), nostra.policies.checkpoint is complete: no partially initialised module on the way."""
    code = ("import sys; import nostra.policies.checkpoint as c; "
            "assert c.POLICIES and c.load_runner and c.CHECKPOINT_FORMAT; "
            "assert 'nostra.policies.base' in sys.modules")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_rollouts_load_a_policy_without_importing_lightning(tmp_path):
    """What an evaluation worker imports (the runners, checkpoint loading, the episode engine) leaves
    Lightning out: it costs seconds at every process start. Training still gets it on use."""
    import numpy as np
    import torch

    from conftest import small_net
    from nostra.modality import sim_observations
    from nostra.policies.modules import policy_module

    mods = [m for m in sim_observations(36).modalities if m.kind == "lowdim"]
    module = policy_module("lstm")(mods, 7, net=small_net("lstm"))
    dims = {m.name: m.shape for m in mods} | {"actions": (7,)}
    module.set_normalization({k: {"mean": np.zeros(d), "std": np.ones(d)} for k, d in dims.items()})
    ckpt = {"state_dict": module.state_dict()}
    module.on_save_checkpoint(ckpt)
    torch.save(ckpt, tmp_path / "lstm.ckpt")
    code = ("import sys; import nostra.sim.rollout, nostra.workflows.evaluation, nostra.episode; "
            "from nostra.policies.checkpoint import load_runner; "
            f"r = load_runner({str(tmp_path / 'lstm.ckpt')!r}); r.reset(); "
            "assert 'lightning' not in sys.modules, [m for m in sys.modules if m.startswith('lightning')][:5]; "
            "from nostra.policies.modules import NostraPolicy; assert 'lightning' in sys.modules")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
