"""The import contract in pyproject.toml ([tool.importlinter]): the house keeps it, and a
forbidden import breaks it (so the build fails on one)."""
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.live

pytest.importorskip("importlinter", reason="import-linter is not installed (pip install '.[test]')")

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("sitl", "vehicles", "ground_station", "filters")


def _checkout(tmp_path) -> Path:
    if not (ROOT / "pyproject.toml").is_file() or not all((ROOT / p).is_dir() for p in PACKAGES):
        pytest.skip("needs the source tree (tests/ beside sitl/, vehicles/, ground_station/, filters/)")
    for p in PACKAGES:
        shutil.copytree(ROOT / p, tmp_path / p, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path


def _lint(where: Path):
    code = ("import sys; from importlinter.cli import lint_imports; "
            "sys.exit(lint_imports(config_filename='pyproject.toml', no_cache=True))")
    return subprocess.run([sys.executable, "-c", code], cwd=where, env={"PYTHONPATH": str(where), "PATH": ""},
                          capture_output=True, text=True, timeout=120)


def test_the_house_keeps_its_import_contract(tmp_path):
    r = _lint(_checkout(tmp_path))
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert "broken" in r.stdout and "0 broken" in r.stdout


@pytest.mark.parametrize("module, line, contract", [
    # the plumbing reaching up into the composition root
    ("sitl/bus/schema.py", "import sitl.app.cli", "Layers"),
    # a component reaching into the composition root (an experiment's tuning)
    ("ground_station/node.py", "from sitl.app.experiments import sonde", "Layers"),
    # one component importing the other
    ("vehicles/beacon.py", "import ground_station.node", "Layers"),
    # the estimator doing I/O
    ("filters/ekf.py", "import zenoh", "Estimation is pure"),
])
def test_a_forbidden_import_breaks_the_contract(tmp_path, module, line, contract):
    where = _checkout(tmp_path)
    p = where / module
    p.write_text(p.read_text(encoding="utf-8") + f"\n{line}  # a forbidden import\n", encoding="utf-8")
    r = _lint(where)
    assert r.returncode != 0, r.stdout[-3000:]
    broken = r.stdout.partition("Broken contracts")[2]
    assert "1 broken" in r.stdout and contract in broken, r.stdout[-3000:]
    assert module.removesuffix(".py").replace("/", ".") in broken  # the report names the importer
