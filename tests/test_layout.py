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


def test_the_core_imports_nothing_from_eval():
    # the commands reach the `ablation` and `eval` commands by name (`cli/main.py`), never by import
    core = [p for p in SOURCES if p.relative_to(ROOT).parts[0] == "ragsplat_core"]
    bad = {p.relative_to(ROOT).as_posix() for p in core if any(m == "eval" or m.startswith("eval.")
                                                             for m in imported_modules(p))}
    assert not bad, f"{sorted(bad)} import eval"


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
    "class SpecError(", "def extract_surface(", "NODATA = ",
    '"@@ragsplat ', "def training_bar(", "os.replace(",
])
def test_one_definition(pattern):
    where = [p.relative_to(ROOT).as_posix() for p in SOURCES if pattern in p.read_text()]
    assert len(where) == 1, f"{pattern!r} in {where}"


def test_version_and_command_order(capsys):
    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0 and capsys.readouterr().out.startswith("ragsplat ")
    assert list(COMMANDS) == ["dataset", "train", "render", "eval", "score", "ablation", "export", "survey",
                             "stability", "bench"]


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
    (["dataset", "--out", "d", "--seed", "-5"], "--seed"),
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
    for argv in (["stability", "--out", str(tmp_path)], ["train", "--data", "d", "--out", str(tmp_path / "file")]):
        with pytest.raises(SystemExit) as done:
            main(argv)
        assert done.value.code == 2 and "--out" in capsys.readouterr().err
    assert (tmp_path / "file").read_text() == "mine"


def test_interrupt_and_os_errors_are_one_line(tmp_path, monkeypatch, capsys):
    from ragsplat_core.cli import stability

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
