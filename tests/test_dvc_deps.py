"""dvc.yaml's deps are honest: every stage depends on all the code it imports and on every conf
file it reads, so `dvc repro` never reuses a result that a code or config change made stale.

The import and config sets are derived from the code, not listed here: the modules that
pipeline/<stage>.py imports (transitively, through nostra/, retrieval/ and pipeline/, with the
packages' __init__ files), and the conf files that the stage composes and reads (the `cfg.<key>`
chains of its pipeline modules, followed through ${...} interpolations of the composed config).
Adding an import or a config read that no dep covers fails here."""

import ast
import functools
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml
from dvc.repo import Repo
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import pipeline._hydra  # noqa: F401  registers the typed-config schemas that conf/model and conf/train extend

ROOT = Path(__file__).resolve().parents[1]
LOCAL_PACKAGES = ("nostra", "pipeline", "retrieval")
CFG_METHODS = {"get", "items", "keys", "values", "pop", "setdefault"}


# --- what dvc.yaml says ----------------------------------------------------------------------------

def _stages(root: Path) -> dict:
    """stage address -> (cmd, [dep paths relative to root]), with dvc's own resolution of dvc.yaml."""
    repo = Repo(str(root))
    try:
        return {s.addressing: (s.cmd, [Path(d.def_path).as_posix() for d in s.deps]) for s in repo.index.stages}
    finally:
        repo.close()


def _covered(path: str, deps: list[str]) -> bool:
    return any(path == d or path.startswith(d.rstrip("/") + "/") for d in deps)


@pytest.fixture(scope="module")
def stages():
    st = _stages(ROOT)
    assert st, "no stages parsed from dvc.yaml"
    return st


def _nostra_stages(stages) -> dict:
    """address -> (pipeline stage name, overrides, deps) for every `nostra <stage> ...` command."""
    out = {}
    for addr, (cmd, deps) in stages.items():
        argv = shlex.split(cmd)
        assert argv[0] == "nostra", f"{addr}: not a `nostra <stage>` command: {cmd}"
        out[addr] = (argv[1], argv[2:], deps)
    return out


# --- what the code imports -------------------------------------------------------------------------

def _module_file(mod: str) -> Path | None:
    p = ROOT.joinpath(*mod.split("."))
    if (p / "__init__.py").is_file():
        return p / "__init__.py"
    return p.with_suffix(".py") if p.with_suffix(".py").is_file() else None


@functools.cache
def _imports(path: Path, mod: str) -> frozenset[str]:
    """Every module named by an import anywhere in the file (function-level ones too); for
    `from a import b` both a and a.b (b may be a submodule)."""
    pkg = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = pkg.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([node.module] if node.module else []))
            else:
                base = node.module
            out.add(base)
            out |= {f"{base}.{a.name}" for a in node.names}
    return frozenset(out)


def import_closure(start: str) -> dict[str, Path]:
    """module -> file of every project module that importing `start` loads."""
    seen: dict[str, Path] = {}
    todo = [start]
    while todo:
        mod = todo.pop()
        if mod in seen or mod.split(".")[0] not in LOCAL_PACKAGES:
            continue
        f = _module_file(mod)
        if f is None:       # a name imported from a module, not a module
            continue
        seen[mod] = f
        parts = mod.split(".")
        todo += [".".join(parts[:i]) for i in range(1, len(parts))]   # parent packages' __init__
        todo += _imports(f, mod)
    return seen


@functools.cache
def _stage_code(stage: str) -> dict[str, Path]:
    code = import_closure(f"pipeline.{stage}")
    code.update(import_closure("pipeline.cli"))    # the `nostra` console script (pyproject.toml)
    return code


# --- what the stage reads of the config -------------------------------------------------------------

def _cfg_reads(files) -> set[tuple[str, ...]]:
    """Config paths read in these files: the longest static attribute chain on a name `cfg`
    (cfg.data.store -> (data, store); `e = cfg.evaluate` -> (evaluate,), i.e. all of it)."""
    reads = set()
    for f in files:
        tree = ast.parse(f.read_text())
        calls = {id(n.func) for n in ast.walk(tree) if isinstance(n, ast.Call)}
        parents = {id(c): p for p in ast.walk(tree) for c in ast.iter_child_nodes(p)}
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Name) and node.id == "cfg"):
                continue
            chain, cur = [], node
            while isinstance(parents.get(id(cur)), ast.Attribute):
                cur = parents[id(cur)]
                if cur.attr in CFG_METHODS and id(cur) in calls:
                    break
                chain.append(cur.attr)
            if chain:
                reads.add(tuple(chain))
    return reads


_REF = re.compile(r"\$\{([^${}]*)")


def _refs(value) -> set[tuple[str, ...]]:
    """Config paths that ${...} interpolations in a (unresolved) config value refer to."""
    if isinstance(value, dict):
        return set().union(*map(_refs, value.values())) if value else set()
    if isinstance(value, list):
        return set().union(*map(_refs, value)) if value else set()
    out = set()
    if isinstance(value, str):
        for m in _REF.finditer(value):
            body = m.group(1).strip()
            if ":" in body:        # a resolver; only oc.select's first argument is a config path
                name, _, args = body.partition(":")
                if name != "oc.select":
                    continue
                body = args.split(",")[0].strip()
            if body and not body.startswith("."):
                out.add(tuple(body.split(".")))
    return out


def _select(cfg, path):
    node = cfg
    for k in path:
        if not OmegaConf.is_dict(node) or k not in node:
            return None
        node = node._get_node(k)
        if not OmegaConf.is_config(node):
            return node._value() if hasattr(node, "_value") else node
    return OmegaConf.to_container(node, resolve=False)


@functools.cache
def conf_reads(stage: str, overrides: tuple[str, ...]) -> tuple[frozenset[str], object]:
    """The conf files (relative to the root) that the stage's composed config takes the keys it
    reads from, with the composed config."""
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=list(overrides), return_hydra_config=True)
    choices = OmegaConf.to_container(cfg.hydra.runtime.choices)
    pipeline_files = [f for m, f in _stage_code(stage).items() if m.startswith("pipeline.")]
    todo = list(_cfg_reads(pipeline_files))
    seen: set[tuple[str, ...]] = set()
    while todo:
        path = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        todo += _refs(_select(cfg, path))

    # who sets each top-level key: the root config, the chosen option of a group, and any chosen
    # option packaged _global_ (an experiment sets evaluate.*, train.*, setting)
    setters: dict[str, set[str]] = {}
    root = yaml.safe_load((ROOT / "conf/config.yaml").read_text())
    for key in root:
        setters.setdefault(key, set()).add("conf/config.yaml")
    for group, option in choices.items():
        f = ROOT / "conf" / group / f"{option}.yaml"
        if option is None or not f.is_file():      # hydra's own groups
            continue
        rel = f.relative_to(ROOT).as_posix()
        text = f.read_text()
        if "@package _global_" in text:
            for key in yaml.safe_load(text) or {}:
                if key != "defaults":
                    setters.setdefault(key, set()).add(rel)
        else:
            setters.setdefault(group, set()).add(rel)
    files = {"conf/config.yaml"}
    for path in seen:
        files |= setters.get(path[0], set())
    return frozenset(files), cfg


# --- the checks ---------------------------------------------------------------------------------

def test_every_stage_depends_on_all_the_code_it_imports(stages):
    missing = {}
    for addr, (stage, _, deps) in _nostra_stages(stages).items():
        assert (ROOT / "pipeline" / f"{stage}.py").is_file(), f"{addr}: no pipeline/{stage}.py"
        files = sorted(f.relative_to(ROOT).as_posix() for f in _stage_code(stage).values())
        gap = [f for f in files if not _covered(f, deps)]
        if gap:
            missing[addr] = gap
    assert not missing, f"stages that import code no dep covers: {missing}"


def test_every_stage_depends_on_the_conf_files_it_reads(stages):
    missing = {}
    for addr, (stage, overrides, deps) in _nostra_stages(stages).items():
        files, _ = conf_reads(stage, tuple(overrides))
        gap = sorted(f for f in files if not _covered(f, deps))
        if gap:
            missing[addr] = gap
    assert not missing, f"stages that read conf files no dep covers: {missing}"


def test_stages_that_read_the_store_depend_on_it(stages):
    for addr, (stage, overrides, deps) in _nostra_stages(stages).items():
        _, cfg = conf_reads(stage, tuple(overrides))
        reads = (stage in ("index", "retrieve", "train")
                 or (stage == "evaluate" and cfg.evaluate.offline.enabled))
        if reads:
            store = OmegaConf.to_container(cfg.data, resolve=True)["store"]
            assert _covered(store, deps), f"{addr} reads the store {store} but does not depend on it"


def test_the_derivation_sees_what_the_issue_found_missing():
    """The sets the checks above rely on are not vacuous: training imports nostra/data and the
    policies, evaluation imagination, and a train run reads the model, data and train groups."""
    train = {f.relative_to(ROOT).as_posix() for f in _stage_code("train").values()}
    assert {"nostra/data/stats.py", "nostra/policies/base.py", "nostra/models/rssm.py",
            "pipeline/evaluate.py", "pipeline/_hydra.py"} <= train
    evaluate = {f.relative_to(ROOT).as_posix() for f in _stage_code("evaluate").values()}
    assert {"nostra/policies/imagination.py", "nostra/policies/checkpoint.py", "nostra/data/stats.py"} <= evaluate
    files, _ = conf_reads("train", ("model=lstm", "task=lift", "profile=tiny"))
    assert {"conf/config.yaml", "conf/model/lstm.yaml", "conf/data/default.yaml", "conf/train/default.yaml",
            "conf/task/lift.yaml", "conf/profile/tiny.yaml"} <= files
    assert "conf/model/nostra.yaml" not in files and "conf/launcher/local.yaml" not in files
    files, _ = conf_reads("ingest", ("profile=tiny",))
    assert "conf/ingest/default.yaml" in files and "conf/profile/tiny.yaml" not in files


def test_editing_nostra_data_changes_a_dep_hash_of_every_train_and_evaluate_stage(tmp_path):
    """With dvc itself on a copy of the tracked files: appending a comment to nostra/data/stats.py
    changes a dep hash of every train and evaluate stage (dvc would rerun them), while bytecode
    written beside the sources changes none (.dvcignore)."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                            capture_output=True, check=True).stdout.decode().split("\0")
    for rel in filter(None, listed):
        src = ROOT / rel
        if src.is_file():
            (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, tmp_path / rel)
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)

    def dep_hashes():
        repo = Repo(str(tmp_path))
        try:
            return {s.addressing: {d.def_path: d.get_hash().value for d in s.deps if d.exists}
                    for s in repo.index.stages}
        finally:
            repo.close()

    before = dep_hashes()
    (tmp_path / "nostra/__pycache__").mkdir(exist_ok=True)
    (tmp_path / "nostra/__pycache__/stats.cpython-311.pyc").write_bytes(b"\0bytecode")
    (tmp_path / "nostra/data/__pycache__").mkdir(exist_ok=True)
    (tmp_path / "nostra/data/__pycache__/stats.cpython-311.pyc").write_bytes(b"\0bytecode")
    assert dep_hashes() == before, "bytecode counts as a change of the code deps"

    with open(tmp_path / "nostra/data/stats.py", "a") as f:
        f.write("\n# an edit\n")
    after = dep_hashes()
    changed = {addr for addr in before if before[addr] != after[addr]}
    cmds = {addr: cmd for addr, (cmd, _) in _stages(tmp_path).items()}
    expected = {addr for addr, cmd in cmds.items() if cmd.split()[1] in ("generate", "train", "evaluate", "ingest", "index",
                                                                         "retrieve")}
    assert {a for a in cmds if a.startswith(("pretrain", "finetune", "cotrain", "evaluate"))} <= expected
    assert changed == expected, (sorted(expected - changed), sorted(changed - expected))


def test_dvc_lock_is_local_state_that_dvc_accepts():
    """dvc.lock is git-ignored (a run of `make demo` leaves git status clean), and dvc still reads
    it: without core.no_scm dvc refuses a git-ignored lock (FileIsGitIgnored) on every command."""
    ignored = subprocess.run(["git", "check-ignore", "-q", "dvc.lock"], cwd=ROOT)
    assert ignored.returncode == 0, "dvc.lock is not git-ignored"
    from dvc.dvcfile import Lockfile

    repo = Repo(str(ROOT))
    try:
        Lockfile(repo, str(ROOT / "dvc.lock")).load()  # raises FileIsGitIgnored under git integration
    finally:
        repo.close()
