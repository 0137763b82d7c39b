"""The project as a user meets it: README quick start, CI script, wheel contents, CLI basics."""

import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def quick_start_commands():
    """The command lines of the README's quick-start block."""
    text = (ROOT / "README.md").read_text()
    block = re.search(r"## Quick start.*?```(?:bash|sh)?\n(.*?)```", text, re.S)
    assert block, "README.md has no '## Quick start' code block"
    return [line for line in block.group(1).splitlines() if line.strip() and not line.startswith("#")]


def test_quick_start_is_two_commands_and_ci_runs_the_test_one():
    commands = quick_start_commands()
    assert len(commands) == 2
    assert "fsswarp " in commands[0]
    ci_lines = [line for line in (ROOT / ".ci/run").read_text().splitlines()
                if line.strip() and not line.startswith(("#", "set ", "cd ", "bash .ci/"))]
    assert ci_lines == [commands[1]]
    assert "pytest" in commands[1]


def test_wheel_ships_the_kernel_sources(tmp_path):
    """The wheel carries kernels/ as fsswarp/kernels (hatchling force-include)."""
    subprocess.run([sys.executable, "-m", "build", "--wheel", "--no-isolation", "--outdir", str(tmp_path), str(ROOT)],
                   check=True, capture_output=True)
    wheel = next(tmp_path.glob("fsswarp-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    sources = sorted(p.name for p in (ROOT / "kernels").iterdir() if p.suffix in (".cl", ".h"))
    assert sources, "kernels/ holds no OpenCL sources"
    for name in sources:
        assert f"fsswarp/kernels/{name}" in names
    assert "fsswarp/cli.py" in names


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "fsswarp", *args], capture_output=True, text=True, cwd=cwd)


def test_help_explains_every_command():
    done = run_cli("--help")
    assert done.returncode == 0
    for command in ("info", "check", "scene"):
        assert command in done.stdout
    for command in ("info", "check", "scene"):
        sub = run_cli(command, "--help")
        assert sub.returncode == 0 and "Usage" in sub.stdout


def test_the_command_line_starts_without_the_mesh_and_image_libraries():
    """``fsswarp --help`` (and every command's start, every worker process's) imports fsswarp
    without trimesh, scipy, manifold3d, scikit-image or the GPU runtimes: they are imported
    where used (``--help`` 0.37 s against 1.5 s on a 2-core Xeon)."""
    heavy = ("trimesh", "scipy", "manifold3d", "skimage", "networkx", "matplotlib", "warp", "pyopencl")
    done = subprocess.run([sys.executable, "-c", "import sys, fsswarp.cli; print(' '.join(sorted("
                           f"{{m.split('.')[0] for m in sys.modules}} & set({heavy!r}))))"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "", done.stdout + done.stderr


@pytest.mark.parametrize("args, needle", [
    (("nosuchcommand",), "nosuchcommand"),
    (("--backend", "cuda-magic", "info"), "--backend"),
    (("check", "no/such/path"), "no/such/path"),
    (("scene", "reef", "--out", "x.toml"), "reef"),
    (("scene", "coral-one", "--out", "x.txt"), "x.txt"),
    (("scene", "coral-one", "--positions", "SNX", "--out", "x.toml"), "--positions = 'SNX'"),
    (("--backend", "warp", "--device", "cuda:7", "info"), "cuda:7"),
    (("--backend", "opencl", "--device", "nosuchdevice", "info"), "nosuchdevice"),
    (("check", "/dev/null"), "is neither a regular file nor a folder"),
    (("carve", "ds", "--out", "x", "--box", "1", "2", "3"), "(see 'fsswarp carve --help')"),  # click gives no ctx
    (("check", "n" * 300), "File name too long"),  # an OSError of a path: one line, not a traceback
    (("check", "n" * 300 + ".toml"), "File name too long"),
    (("scene", "table", "--out", "n" * 300 + "/x.toml"), "File name too long"),
])
def test_user_mistakes_exit_2_with_one_line(tmp_path, args, needle):
    done = run_cli(*args, cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in done.stderr
    assert list(tmp_path.iterdir()) == []


def test_scene_positions_writes_the_scene_on_that_rig(tmp_path):
    done = run_cli("scene", "coral-one", "--positions", "ew", "--out", "rig.toml", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "coral-one, 16 views" in done.stdout
    from fsswarp.dataset import load_scene

    names = [view.name for view in load_scene(tmp_path / "rig.toml").rig.views]
    assert names[0] == "Em90" and names[8] == "Wm90" and len(names) == 16
