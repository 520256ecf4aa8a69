"""The package's layout promises, checked from its source: one module names the run directory's files."""

from __future__ import annotations

import ast
from pathlib import Path

import trajflow_pipeline

PACKAGE = Path(trajflow_pipeline.__file__).parent
#: the run directory's own file and folder names (the model file's name belongs to model/checkpoint.py, the
#: checkpoint format's owner; config.toml and metrics.parquet also name files of an experiment directory)
RUN_DIR_NAMES = ("run.json", "train_log", "state.pt", "end-", "best-", "lowest-val-loss-", "checkpoints", "eval.json",
                 "predictions.parquet", "ground_truth.parquet", "eval-cache", ".eval.lock")


def string_constants(path: Path) -> list[tuple[int, str]]:
    """(line, text) of every string literal in a module that could be a path (no whitespace: messages and help
    texts may mention a file for people) and is not a docstring."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                  and node.body and isinstance(node.body[0], ast.Expr)
                  and isinstance(node.body[0].value, ast.Constant)}
    return [(node.lineno, node.value) for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings
            and not any(character.isspace() for character in node.value)]


def test_only_rundir_names_the_run_directory_files() -> None:
    owner = PACKAGE / "rundir.py"
    found = [f"{path.relative_to(PACKAGE)}:{line}: {text!r}"
             for path in sorted(PACKAGE.rglob("*.py")) if path != owner
             for line, text in string_constants(path) if any(name in text for name in RUN_DIR_NAMES)]
    assert not found, "run-directory file names outside rundir.py:\n" + "\n".join(found)
    assert any("run.json" in text for _, text in string_constants(owner))


def test_the_model_names_the_config_accepts_are_the_model_families() -> None:
    """config.MODEL_NAMES (what --model and config files accept; the config module cannot import the models) and
    models.MODEL_CLASSES (what builds them) list the same families in the same order."""
    from trajflow_pipeline.model.config import MODEL_NAMES
    from trajflow_pipeline.model.models import MODEL_CLASSES

    assert tuple(MODEL_CLASSES) == MODEL_NAMES


def test_the_readme_layout_names_every_package_and_module_of_the_top_level() -> None:
    """The README's Layout section lists exactly the package's folders and top-level modules (errors and the
    entry points aside)."""
    readme = (PACKAGE.parent / "README.md").read_text(encoding="utf-8")
    block = readme.split("## Layout", 1)[1].split("```")[1]
    listed = {line.split()[0].rstrip("/") for line in block.splitlines()[2:] if line.startswith("  ")}
    present = {path.name for path in PACKAGE.iterdir() if path.is_dir() and (path / "__init__.py").exists()}
    present |= {path.stem + ".py" for path in PACKAGE.glob("*.py")} - {"__init__.py", "__main__.py", "errors.py"}
    present |= {"configs"} if (PACKAGE / "configs").is_dir() else set()
    assert listed == present


def test_the_cli_starts_without_torch() -> None:
    """`trajflow --help` (and any command before it runs) loads no torch: the CLI imports stages and models only
    inside the commands, and the model package loads its submodules on first use."""
    import subprocess
    import sys

    probe = "import sys, trajflow_pipeline.cli.app; print('torch' in sys.modules)"
    child = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True, timeout=120)
    assert child.stdout.strip() == "False"


#: stage -> the stages it chains (runs as a step of its own work); no other module imports a stage
STAGE_CHAINS = {
    "demo": {"experiment", "report"},                # the demo is a quick experiment and its report
    # the data stages are built, each planned run is trained, then evaluated, and the report ends it
    "experiment": {"data_stages", "evaluate", "experiment_config", "report"},
    "data_stages": {"augment", "experiment_config"},  # an experiment's [[augment]] steps run the augment stage
    # reads an experiment's plan and data stages to say where they stand
    "status": {"data_stages", "experiment", "experiment_config"},
    # an experiment's [eval] table is the eval stage's options, its [[augment]] steps the augment stage's
    "experiment_config": {"augment", "evaluate"},
}


def stage_imports(path: Path) -> set[str]:
    """The stage modules (trajflow_pipeline/stages/*.py) module `path` imports, by name."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = path.relative_to(PACKAGE.parent).with_suffix("").parts[:-1]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            base = list(package[:len(package) - node.level + 1]) if node.level else []
            parts = [*base, *(node.module.split(".") if node.module else [])]
            names = [parts + [alias.name] for alias in node.names]
        elif isinstance(node, ast.Import):
            names = [alias.name.split(".") for alias in node.names]
        else:
            continue
        for name in names:
            if name[:2] == ["trajflow_pipeline", "stages"] and len(name) > 2 and name[2] != "__init__":
                found.add(name[2])
    return found


def test_no_module_imports_a_stage_but_its_command_and_the_stages_that_chain_it() -> None:
    """Stages are leaves: the library packages never import one; a stage is imported by its CLI command and by
    the stages that run it as a step (STAGE_CHAINS), nothing else."""
    stages = {path.stem for path in (PACKAGE / "stages").glob("*.py")} - {"__init__"}
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = path.relative_to(PACKAGE)
        for stage in stage_imports(path) & stages:
            if module.parts[0] == "cli":
                continue
            if module.parts[0] == "stages" and stage in STAGE_CHAINS.get(path.stem, set()) | {path.stem}:
                continue
            found.append(f"{module} imports stages/{stage}.py")
    assert not found, "\n".join(found)


def test_the_tests_mirror_the_package() -> None:
    """Every folder of tests/ is named after a package of trajflow_pipeline (tests/model for model/, ...); only
    package-wide checks (this file, the fuzz suite) and conftest.py sit at the top."""
    tests = Path(__file__).resolve().parent
    packages = {path.name for path in PACKAGE.iterdir() if (path / "__init__.py").exists()}
    folders = {path.name for path in tests.iterdir() if path.is_dir() and not path.name.startswith(("_", "."))}
    assert folders and folders <= packages, sorted(folders - packages)
    assert {path.name for path in tests.glob("*.py")} == {"conftest.py", "test_layout.py", "test_fuzz.py"}
