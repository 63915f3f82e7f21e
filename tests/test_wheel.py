"""The wheel works on its own: built from the sources, installed into a clean venv, one clearance episode run.

Offline and quick: the wheel is built without build isolation (this environment's setuptools), and the
clean venv sees the already-installed dependencies through one ``.pth`` line naming a directory of
links to this environment's site-packages minus parcelpick itself (and the dependencies' own ``.pth`` hooks), so
pip still checks every declared dependency (``--no-index``: nothing is downloaded) and the code runs from the
wheel, not the checkout.
"""

from __future__ import annotations

import json
import os
import shutil
import site
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("parcelpick_env", "policies", "eval", "dataset")
SHIPPED_SUFFIXES = (".pt", ".zip", ".safetensors", ".json", ".urdf")
OWN = ("parcelpick", "__editable__", "parcelpick_env", "policies", "eval", "dataset")

pytestmark = pytest.mark.slow


def _run(cmd: list[str], cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    done = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"{' '.join(map(str, cmd))} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel, built from a copy of the sources (so the checkout gets no build/ or egg-info)."""
    src = tmp_path_factory.mktemp("src")
    for name in PACKAGES:
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    dist = tmp_path_factory.mktemp("dist")
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "--no-index",
          "-w", str(dist), str(src)], cwd=src)
    (built,) = dist.glob("parcelpick-*.whl")
    return built


def test_wheel_ships_every_checkpoint_and_the_urdf(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    shipped = [p.relative_to(ROOT).as_posix() for name in ("parcelpick_env", "policies")
               for p in (ROOT / name).rglob("*") if p.suffix in SHIPPED_SUFFIXES and "__pycache__" not in p.parts]
    assert any(s.endswith("ppo_pixel.safetensors") for s in shipped) and any(s.endswith(".urdf") for s in shipped)
    assert sorted(set(shipped) - names) == []


def test_clean_venv_installs_the_wheel_and_runs_a_clearance_episode(wheel, tmp_path):
    deps = tmp_path / "deps"  # this environment's site-packages without parcelpick itself
    deps.mkdir()
    (here,) = [Path(p) for p in site.getsitepackages() if Path(p).name == "site-packages"][:1]
    for entry in here.iterdir():
        if not entry.name.startswith(OWN) and entry.suffix != ".pth":
            (deps / entry.name).symlink_to(entry)
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    python = env_dir / "bin" / "python"
    target = Path(_run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                       cwd=tmp_path).stdout.strip())
    (target / "_parcelpick_deps.pth").write_text(f"{deps}\n")
    for hook in here.glob("*.pth"):  # the dependencies' own path hooks (pinocchio's cmeel prefix), after that line
        if not hook.name.startswith(OWN):
            shutil.copy2(hook, target / hook.name)
    _run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-index", "--find-links",
          str(wheel.parent), "parcelpick"], cwd=tmp_path)

    where = _run([str(python), "-c", "import parcelpick_env, eval.clearance as c; print(parcelpick_env.__file__, c.__file__)"],
                 cwd=tmp_path).stdout.split()
    assert all(Path(w).is_relative_to(env_dir) for w in where), where
    out = tmp_path / "clearance.json"
    _run([str(env_dir / "bin" / "parcelpick-clearance"), "--policy", "diffusion", "--objects", "rectangular",
          "--layout", "scattered", "--episodes", "1", "--parcels", "2", "--max-attempts", "2", "--out", str(out)],
         cwd=tmp_path)
    summary = json.loads(out.read_text())
    assert summary["overall"]["attempts"] >= 1
