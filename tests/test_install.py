"""`pip install .` gives a working visemeflow: a real wheel (not editable) installed into a fresh venv, run from there.

What it does (about 30-60 s, marked `install`; `pytest -m "not install"` leaves it out):
1. builds the wheel from a copy of the working tree (git's tracked and untracked, not ignored files), with the
   shared .venv's setuptools (`pip wheel --no-deps --no-build-isolation`), so the checkout gets no `build/`;
2. creates a venv in a temporary folder and installs the wheel there with `--no-deps`; the dependencies are
   reused from the shared .venv through a `.pth` line that puts its site-packages AFTER the venv's own (a plain
   folder line: the editable install's finder in that folder is not run), so no download and no copy of torch;
3. from a working directory outside the repository, with no PYTHONPATH: imports visemeflow (it must come from the
   temporary venv), loads the demo rig, the identity modes, the recipes and the phoneme tables (package data),
   runs `visemeflow --help`, and ingests two utterances of examples/corpus into a temporary store.
"""

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.install


def run(args, cwd: Path, env: dict, timeout: float = 300) -> subprocess.CompletedProcess:
    done = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"{args}: exit {done.returncode}\n{done.stdout}\n{done.stderr}"
    return done


def source_files() -> list[str]:
    """The working tree as a checkout has it: tracked files and untracked ones git does not ignore."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                            capture_output=True, check=True).stdout.decode().split("\0")
    return [name for name in listed if name and (REPO / name).is_file()]


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    root = tmp_path_factory.mktemp("install")
    env = {key: value for key, value in os.environ.items()
           if not key.startswith(("PYTHON", "PREFECT_", "VIRTUAL_ENV"))}
    env.update(PREFECT_HOME=str(root / "prefect-home"), PREFECT_SERVER_ANALYTICS_ENABLED="false",
               PREFECT_LOGGING_LEVEL="WARNING", PYTHONNOUSERSITE="1")

    src = root / "src"
    files = source_files()
    for name in files:
        (src / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / name, src / name)
    run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation", "--no-index",
         "--wheel-dir", root / "dist", src], cwd=root, env=env)
    (wheel,) = (root / "dist").glob("visemeflow-*.whl")

    venv = root / "venv"
    run([sys.executable, "-m", "venv", "--without-pip", venv], cwd=root, env=env)
    python = venv / "bin" / "python"
    run([sys.executable, "-m", "pip", "--python", python, "install", "--quiet", "--no-deps", "--no-index", wheel],
        cwd=root, env=env)
    site = Path(run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                    cwd=root, env=env).stdout.strip())
    shared = Path(sysconfig.get_paths()["purelib"])          # the shared .venv's, where the dependencies are
    (site / "zz-shared-dependencies.pth").write_text(f"{shared}\n")
    work = root / "elsewhere"
    work.mkdir()
    return {"root": root, "env": env, "wheel": wheel, "venv": venv, "python": python, "site": site.resolve(),
            "work": work, "files": files}


def test_the_wheel_holds_the_package_and_all_its_data_files_and_nothing_else(installed):
    with zipfile.ZipFile(installed["wheel"]) as wheel:
        names = wheel.namelist()
    assert {name.split("/")[0] for name in names} == {"visemeflow", "visemeflow-0.1.0.dist-info"}
    assert not [n for n in names if n.startswith(("tests/", "examples/", "bench/", "docs/")) or "/tests/" in n]
    # every non-Python file of the package (data the code reads) is in the wheel: a new data file that
    # [tool.setuptools.package-data] does not name fails here
    data = {name for name in installed["files"] if name.startswith("visemeflow/") and not name.endswith(".py")}
    assert data and data - set(names) == set()
    for name in ("visemeflow/rig/data/ict_visemes.npz", "visemeflow/rig/data/ict_identities.npz",
                 "visemeflow/rig/data/LICENSE", "visemeflow/rig/data/SOURCE.txt"):
        assert name in names


PROBE = """
import json, sys
import visemeflow
from visemeflow.phonetics.inventory import map_phone
from visemeflow.rig import demo_rig_path, evaluate_rig, load_demo_rig, load_ict_recipes
from visemeflow.tracking.identity import apply_identity, demo_identity_path, load_identity_modes
import numpy as np
rig = load_demo_rig()
modes = load_identity_modes(demo_identity_path())
subject = apply_identity(rig, modes, np.full(modes.n_modes, 0.5, dtype=np.float32))
meshes = evaluate_rig(rig, np.eye(16, dtype=np.float32)[:2])
print(json.dumps({
    "visemeflow": visemeflow.__file__, "rig": str(demo_rig_path()), "identity": str(demo_identity_path()),
    "sys_path": sys.path, "vertices": rig.n_vertices, "modes": modes.n_modes, "subject": subject.n_vertices,
    "meshes": list(meshes.shape), "recipes": len(load_ict_recipes()),
    "phone": str(map_phone("M", "arpabet")),
}))
"""


def test_the_installed_package_loads_its_rig_and_identity_model_from_site_packages(installed):
    out = json.loads(run([installed["python"], "-c", PROBE], cwd=installed["work"], env=installed["env"]).stdout)
    site = installed["site"]
    for key in ("visemeflow", "rig", "identity"):
        assert Path(out[key]).resolve().is_relative_to(site), (key, out[key])
    assert Path(out["rig"]).name == "ict_visemes.npz" and Path(out["identity"]).name == "ict_identities.npz"
    # the checkout is not importable from there: neither the repository nor its package folder is on sys.path
    assert not {str(REPO), str(REPO / "visemeflow")} & {str(Path(p).resolve()) for p in out["sys_path"] if p}
    assert out["vertices"] == out["subject"] == 21984 and out["modes"] == 20
    assert out["meshes"] == [2, 21984, 3] and out["recipes"] == 16
    assert "MBP" in out["phone"]


def test_the_installed_command_runs_a_flow(installed):
    bin_dir = installed["venv"] / "bin"
    env, work = installed["env"], installed["work"]
    help_text = run([bin_dir / "visemeflow", "--help"], cwd=work, env=env).stdout
    assert "ingest" in help_text and "pipeline" in help_text

    corpus = work / "corpus" / "LJ"
    corpus.mkdir(parents=True)
    ids = ["LJ/LJ001-0001", "LJ/LJ001-0002"]
    for uid in ids:
        for suffix in (".wav", ".TextGrid"):
            shutil.copy2(REPO / "examples" / "corpus" / f"{uid}{suffix}", corpus / f"{uid.split('/')[1]}{suffix}")
    store = work / "store"
    run([bin_dir / "visemeflow", "ingest", work / "corpus", "--store", store], cwd=work, env=env)
    table = run([installed["python"], "-c",
                 "import json, sys; from visemeflow.storage import Store; s = Store(sys.argv[1]); "
                 "u = s.read_table('utterances'); p = s.read_table('phones'); "
                 "print(json.dumps({'ids': sorted(u.column('utterance_id').to_pylist()), 'phones': p.num_rows}))",
                 store], cwd=work, env=env).stdout
    result = json.loads(table)
    assert result["ids"] == ids and result["phones"] > 20
