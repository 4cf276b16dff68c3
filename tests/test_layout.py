"""The architecture the README describes, checked on the source tree: commands import the library, never
the reverse; every command is a module of `ragsplat_core/cli` (`ragsplat.cli`), every operational script is
in `tools/`; the data contract imports without torch; each shared fact has exactly one definition. The four
folders install as one package, `ragsplat` (pyproject.toml's package-dir), so the rules below name modules
by their installed names: `ragsplat.X` for ragsplat_core/X.py, `ragsplat.eval.X` for eval/X.py, ..."""

import ast
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from ragsplat.cli.main import COMMANDS, main
from ragsplat.outputs import SOURCE_PACKAGES

ROOT = Path(__file__).resolve().parent.parent
SETUPTOOLS = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
# {folder: its installed package}: ragsplat_core -> ragsplat, eval -> ragsplat.eval, ...
INSTALLED = {folder: package for package, folder in SETUPTOOLS["package-dir"].items()}
PACKAGES = tuple(INSTALLED)  # the folders the wheel installs
OLD_NAMES = {"ragsplat_core", "eval", "datagen", "blender_scenes"}  # their import names before issue 51
SOURCES = [p for d in (*PACKAGES, "tools") for p in (ROOT / d).rglob("*.py")]
COMMAND_LAYER = ROOT / "ragsplat_core" / "cli"


def imported_modules(path: Path) -> set[str]:
    """The modules `path` imports; `from a import b` counts as `a` and `a.b` (b may be a module: `from
    ragsplat import eval` imports the harness)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)
    return names


def within(module: str, *packages: str) -> bool:
    """Whether `module` is one of `packages` or inside one."""
    return any(module == p or module.startswith(p + ".") for p in packages)


def module_name(path: Path) -> str:
    """The installed name of a source file of the packages: ragsplat_core/train/config.py ->
    ragsplat.train.config, eval/__init__.py -> ragsplat.eval."""
    folder, *parts = path.relative_to(ROOT).with_suffix("").parts
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join([INSTALLED[folder], *parts])


def test_one_installed_package():
    # one top-level name, each folder where the design fixes it; nothing imports the old names (the tests'
    # pythonpath has the repository root, where `import eval` would still find the folder)
    assert INSTALLED == {"ragsplat_core": "ragsplat", "eval": "ragsplat.eval", "datagen": "ragsplat.datagen",
                         "blender_scenes": "ragsplat.blender_scenes"} == SOURCE_PACKAGES  # (the digests')
    tests = list((ROOT / "tests").rglob("*.py"))
    old = {p.relative_to(ROOT).as_posix(): names for p in SOURCES + tests
           if (names := sorted(m for m in imported_modules(p) if m.split(".")[0] in OLD_NAMES))}
    assert not old, old


def test_a_wheel_digests_its_sources_as_the_checkout(tmp_path):
    # a wheel nests the folders in ragsplat/ (as pyproject.toml's package-dir maps them); the digests that key
    # the ablation's rows and stamp its results name each file by its source-tree path there too
    import os
    import shutil

    from ragsplat.eval.ablation import CODE, ROW_CODE
    from ragsplat.outputs import source_digest

    site = tmp_path / "site"
    for folder, package in INSTALLED.items():
        shutil.copytree(ROOT / folder, site.joinpath(*package.split(".")), dirs_exist_ok=True,
                        ignore=shutil.ignore_patterns("__pycache__"))
    code = ("import ragsplat; from ragsplat.outputs import source_digest; print(ragsplat.__file__); "
            f"print(source_digest(*{CODE!r})); print(source_digest(*{ROW_CODE!r}))")
    done = subprocess.run([sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": str(site)},
                          cwd=tmp_path, capture_output=True, text=True, check=True)
    where, *digests = done.stdout.split()
    assert Path(where).parent == site / "ragsplat"
    assert digests == [source_digest(*CODE), source_digest(*ROW_CODE)]


def test_the_layers_hold():
    """pyproject.toml's import-linter contracts (the layers, Blender, argparse, the model and the rasterizer),
    run on the package as it installs: its four folders copied under the one name, as the wheel lays them out
    (the linter reads a package from one folder; package-dir maps four into it)."""
    import shutil
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        for folder, package in INSTALLED.items():
            shutil.copytree(ROOT / folder, Path(tmp, *package.split(".")),
                            ignore=shutil.ignore_patterns("__pycache__"))
        lint = subprocess.run([Path(sys.executable).parent / "lint-imports", "--no-cache",
                               ROOT / "pyproject.toml"], check=False, cwd=tmp,
                              env={**os.environ, "PYTHONPATH": tmp}, capture_output=True, text=True)
    assert lint.returncode == 0, lint.stdout[-3000:] + lint.stderr[-2000:]
    assert "0 broken" in lint.stdout


def test_no_tool_imports_the_command_layer_or_blender():
    # the packages' own imports are the contracts' (`test_the_layers_hold`); the tools are not installed
    tools = [p for p in SOURCES if p.relative_to(ROOT).parts[0] == "tools"]
    bad = {p.relative_to(ROOT).as_posix() for p in tools
           if any(within(m, "ragsplat.cli", "bpy", "mathutils") for m in imported_modules(p))}
    assert not bad, f"{sorted(bad)} import ragsplat.cli or Blender"


def test_the_installed_packages_import_no_tool():
    bad = {p.relative_to(ROOT).as_posix() for p in SOURCES if p.relative_to(ROOT).parts[0] != "tools"
           and any(m.split(".")[0] == "tools" for m in imported_modules(p))}
    assert not bad, f"{sorted(bad)} import tools"


def test_no_tool_imports_another():
    # what two tools share is the library's (the package `tools` itself only sets the OpenMP wait)
    tools = [p for p in SOURCES if p.relative_to(ROOT).parts[0] == "tools" and p.name != "__init__.py"]
    bad = {p.relative_to(ROOT).as_posix() for p in tools
           if any(within(m, "tools") and m != "tools" for m in imported_modules(p))}
    assert not bad, f"{sorted(bad)} import another tool"


def test_every_command_is_one_module_of_the_command_layer():
    helpers = {"__init__", "main", "args", "progress", "cluster"}  # the entry point and what commands share
    modules = {name: module for name, (module, _) in COMMANDS.items()}
    assert all(m.startswith("ragsplat.cli.") for m in modules.values()), modules
    assert len(set(modules.values())) == len(modules)  # one module per subcommand
    for name, module in modules.items():
        tree = ast.parse((COMMAND_LAYER / f"{module.rsplit('.', 1)[1]}.py").read_text())
        defined = {node.name for node in tree.body if isinstance(node, ast.FunctionDef)}
        assert {"add_arguments", "run"} <= defined, f"ragsplat {name}: {module} lacks {{add_arguments, run}}"
    files = {p.stem for p in COMMAND_LAYER.glob("*.py")}
    assert (files - helpers
            == {m.rsplit(".", 1)[1] for m in modules.values()}), "a command module not in COMMANDS"


def runs_as_script(path: Path) -> bool:
    """Whether the module has an `if __name__ == "__main__":` block."""
    return any(isinstance(node, ast.If) and isinstance(node.test, ast.Compare)
               and isinstance(node.test.left, ast.Name) and node.test.left.id == "__name__"
               for node in ast.parse(path.read_text()).body)


def test_scripts_are_commands_or_tools():
    # an operational script (`python -m tools.NAME`) lives in tools/; in the installed packages only the entry
    # point and the renderer (the Blender process's own script) run as scripts
    scripts = {p.relative_to(ROOT).as_posix() for p in SOURCES
               if p.relative_to(ROOT).parts[0] != "tools" and runs_as_script(p)}
    assert scripts == {"ragsplat_core/cli/main.py", "blender_scenes/render.py"}
    assert not [p for d in PACKAGES for p in (ROOT / d).rglob("*.sh")], "a shell script outside tools/"


def test_the_wheel_holds_every_package_and_no_tool():
    # pyproject.toml lists the packages (a mapped folder cannot be found by pattern): every folder of the
    # four with an __init__.py, under its installed name, and nothing else (no tool)
    folders = {module_name(p) for d in PACKAGES for p in (ROOT / d).rglob("__init__.py")}
    assert set(SETUPTOOLS["packages"]) == folders
    assert all(within(name, "ragsplat") for name in SETUPTOOLS["packages"])


def import_graph() -> dict[str, set[str]]:
    """{module: the installed modules it imports}, for every module of the installed packages. Every import
    counts, the ones inside functions and under TYPE_CHECKING too: a lazy import is still an arrow."""
    modules = {}
    for path in (p for package in PACKAGES for p in (ROOT / package).rglob("*.py")):
        modules[module_name(path)] = path
    graph = {}
    for name, path in modules.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module:  # `from pkg import module` names a module
                targets.update(f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in modules
                               else node.module
                               for a in node.names)
        graph[name] = {t for t in targets if t in modules and t != name}
    return graph


def test_no_import_circle():
    graph = import_graph()
    assert {"ragsplat.gaussians", "ragsplat.raster.backends", "ragsplat.datagen.spec",
            "ragsplat.eval.ablation", "ragsplat.blender_scenes.render"} <= set(graph)  # the walk found them
    done, path = set(), []

    def visit(module):  # depth first; a module met again on the current path closes a circle
        if module in path:
            pytest.fail("import circle: " + " -> ".join(path[path.index(module):] + [module]))
        if module in done:
            return
        path.append(module)
        for target in sorted(graph[module]):
            visit(target)
        path.pop()
        done.add(module)

    for module in sorted(graph):
        visit(module)


def test_code_names_no_issue():
    # a comment says why; which issue asked for it is history, kept in docs and the log
    import re

    said = re.compile(r"\bissues? \d|\bissue's\b", re.IGNORECASE)
    bad = [f"{p.relative_to(ROOT).as_posix()}:{k}" for p in SOURCES
           for k, line in enumerate(p.read_text().splitlines(), 1) if said.search(line)]
    assert not bad, f"issue references in code: {bad}"


def test_data_contract_and_generator_import_without_torch():
    code = ("import sys; import ragsplat.datagen.build, ragsplat.cli.generate, ragsplat.dataset.layout, "
            "ragsplat.datagen.job; "
            "import ragsplat; ragsplat.dataset; "
            "assert 'torch' not in sys.modules, 'torch was imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


@pytest.mark.parametrize("env, spin", [({}, "2000"), ({"GOMP_SPINCOUNT": "50"}, "50"),
                                       ({"OMP_WAIT_POLICY": "PASSIVE"}, None)])
def test_commands_and_tools_set_the_openmp_wait_before_torch(env, spin):
    # a tool run beside others (tools.tune's rows on one machine) waits as the `ragsplat` command does; the
    # user's own setting wins
    code = "import os, sys, tools; assert 'torch' not in sys.modules; print(os.environ.get('GOMP_SPINCOUNT'))"
    clean = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}
    out = subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, capture_output=True, text=True,
                         env={**clean, **env}).stdout.split()
    assert out == [str(spin)]


@pytest.mark.parametrize("pattern", [
    "def quat_to_rotmat(", "def covariance(", "def psnr(", "def versions(", "def temp_path(",
    "def atomic_path(",
    "def ground_offset(", "math.asin(", "def footprint(cameras", "VARIANTS: dict", "class DatasetError(",
    "class SpecError(", "def extract_surface(", "NODATA = ", "INIT = ", "JOBS = ", "CLEAR_VARIANTS = ",
    '"@@ragsplat ', "def training_bar(", "os.replace(",
])
def test_one_definition(pattern):
    where = [p.relative_to(ROOT).as_posix() for p in SOURCES if pattern in p.read_text()]
    assert len(where) == 1, f"{pattern!r} in {where}"


def test_version_and_command_order(capsys):
    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0 and capsys.readouterr().out.startswith("ragsplat ")
    assert list(COMMANDS) == ["generate", "train", "render", "score", "ablation", "sweep", "export",
                             "survey", "stability", "bench"]


def test_library_error_is_one_line_and_exit_2(tmp_path, capsys):
    assert main(["train", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ragsplat train: error: ") and "does not exist" in err[0]


@pytest.mark.parametrize("argv, option", [
    (["bench", "refraction", "--cases", "0"], "--cases"),
    (["bench", "refraction", "--repeats", "0"], "--repeats"),
    (["bench", "raster", "--n", "-5"], "--n"),
    (["bench", "raster", "--size", "0"], "--size"),
    (["bench", "raster", "--repeats", "0"], "--repeats"),
    (["bench", "train-step", "--counts", "0"], "--counts"),
    (["bench", "train-step", "--steps", "0"], "--steps"),
    (["stability", "--cases", "0"], "--cases"),
    (["generate", "--out", "d", "--seed", "-5"], "--seed"),
    (["train", "--data", "d", "--out", "r", "--iterations", "0"], "--iterations"),
    (["train", "--data", "d", "--out", "r", "--init-depth", "1e400"], "--init-depth"),
    (["train", "--data", "d", "--out", "r", "--backend", "tpu"], "--backend"),
    (["ablation", "--data", "d", "--out", "r", "--variants", "nope"], "--variants"),
])
def test_bad_arguments_stop_before_any_work(argv, option, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as done:
        main(argv)
    err = capsys.readouterr().err
    assert done.value.code == 2 and option in err.splitlines()[-1]
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_outputs_of_the_wrong_kind(tmp_path, capsys):
    (tmp_path / "file").write_text("mine")
    for argv in (["stability", "--out", str(tmp_path)],
                 ["train", "--data", "d", "--out", str(tmp_path / "file")]):
        with pytest.raises(SystemExit) as done:
            main(argv)
        assert done.value.code == 2 and "--out" in capsys.readouterr().err
    assert (tmp_path / "file").read_text() == "mine"


def test_interrupt_and_os_errors_are_one_line(tmp_path, monkeypatch, capsys):
    from ragsplat.cli import stability

    def interrupted(args):
        raise KeyboardInterrupt

    def no_space(args):
        raise OSError(28, "No space left on device", str(tmp_path / "report.json"))

    for run, code, phrase in ((interrupted, 130, "interrupted"), (no_space, 2, "No space left on device")):
        monkeypatch.setattr(stability, "run", run)
        assert main(["stability", "--out", str(tmp_path / "report.json")]) == code
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and phrase in err[0] and err[0].startswith("ragsplat stability: ")
    with pytest.raises(OSError):  # --debug: the traceback
        main(["stability", "--out", str(tmp_path / "report.json"), "--debug"])


def test_dataset_file_stands_for_its_directory(tmp_path, capsys):
    data = tmp_path / "data"
    data.mkdir()
    (data / "transforms.json").write_text("{")
    assert main(["train", "--data", str(data / "transforms.json"), "--out", str(tmp_path / "run")]) == 2
    assert f"{data / 'transforms.json'}: not valid JSON" in capsys.readouterr().err


def test_unavailable_benchmark_backend_is_one_line(capsys):
    assert main(["bench", "raster", "--backends", "gsplat-on-abacus"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gsplat-on-abacus is not available here" in err[0]


def test_markdown_tables_become_blocks():
    from ragsplat.pages import markdown_blocks

    text = "# Table 1\n\nA note\nthat wraps.\n\n| a | b |\n| --- | ---: |\n| 1 | 2 |\n| 3 | 4 |\nAfter.\n"
    assert markdown_blocks(text) == [{"heading": "Table 1"}, {"text": "A note that wraps."},
                                     {"table": {"head": ["a", "b"], "rows": [["1", "2"], ["3", "4"]]}},
                                     {"text": "After."}]
