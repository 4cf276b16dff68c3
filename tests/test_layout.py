"""The architecture the README describes, checked on the source tree: commands import the library, never
the reverse; the data contract imports without torch; each shared fact has exactly one definition."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from ragsplat_core.cli.main import COMMANDS, main

ROOT = Path(__file__).resolve().parent.parent
LIBRARY = [p for p in (ROOT / "ragsplat_core").rglob("*.py") if "cli" not in p.relative_to(ROOT).parts[1:2]]
SOURCES = [p for d in ("ragsplat_core", "datagen", "eval", "blender_scenes") for p in (ROOT / d).rglob("*.py")]


def imported_modules(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


def test_library_imports_no_command_layer():
    for path in LIBRARY:
        bad = {m for m in imported_modules(path)
               if m == "argparse" or m.startswith(("ragsplat_core.cli", "eval", "datagen"))}
        assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"


def test_only_the_renderer_imports_bpy():
    users = {p.relative_to(ROOT).as_posix() for p in SOURCES if {"bpy", "mathutils"} & imported_modules(p)}
    assert users == {"blender_scenes/render.py"}


def test_data_contract_and_generator_import_without_torch():
    code = ("import sys; import datagen.build, datagen.cli, ragsplat_core.dataset.layout, blender_scenes.protocol; "
            "import ragsplat_core; ragsplat_core.dataset; "
            "assert 'torch' not in sys.modules, 'torch was imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


@pytest.mark.parametrize("pattern", [
    "def quat_to_rotmat(", "def covariance(", "def psnr(", "def versions(", "def temp_path(", "def atomic_path(",
    "def ground_offset(", "math.asin(", "def footprint(cameras", "VARIANTS: dict", "class DatasetError(",
    "class SpecError(",
    '"@@ragsplat ', "def training_bar(", "os.replace(",
])
def test_one_definition(pattern):
    where = [p.relative_to(ROOT).as_posix() for p in SOURCES if pattern in p.read_text()]
    assert len(where) == 1, f"{pattern!r} in {where}"


def test_version_and_command_order(capsys):
    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0 and capsys.readouterr().out.startswith("ragsplat ")
    assert list(COMMANDS) == ["dataset", "train", "ablation", "stability", "bench"]


def test_library_error_is_one_line_and_exit_2(tmp_path, capsys):
    assert main(["train", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ragsplat train: error: ") and "does not exist" in err[0]
