"""scripts/system-deps.sh: the system packages `make demo`, `make test` and .ci/run need, checked before anything else.

The script runs here with a fake PATH (fake `id`, `ldconfig`, `apt-get`, browser and node), so every case is
tested without touching the machine's packages: nothing missing (no apt call), missing as a normal user (one line
with the install command, exit 1), missing as root (apt-get update + install, checked again). The Makefile tests
show the script runs before the venv is built and before pytest, and that pytest's exit 5 (no tests) passes.
"""

import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "system-deps.sh"
SH = shutil.which("sh") or "/bin/sh"
LN = shutil.which("ln")
ESPEAK_LINE = "\tlibespeak-ng.so.1 (libc6,x86-64) => /lib/x86_64-linux-gnu/libespeak-ng.so.1"
ALL = "espeak-ng chromium nodejs npm curl"


class FakeSystem:
    """A PATH of one folder holding fake tools; `installed` says which of the packages are present."""

    def __init__(self, root: Path, uid: int, installed: set[str], apt_installs: bool = True):
        self.bin = root / "bin"
        self.bin.mkdir()
        self.calls = root / "apt-calls"
        self.libs = root / "ldconfig.txt"
        self.libs.write_text(ESPEAK_LINE + "\n" if "espeak-ng" in installed else "")
        self._tool("id", f"echo {uid}")
        # ldconfig -p lists the cache: here the lines of ldconfig.txt (shell builtins only, PATH has no cat)
        self._tool("ldconfig", f'while IFS= read -r line; do echo "$line"; done < "{self.libs}"')
        for name in ("chromium", "node", "npm", "curl"):
            if {"chromium": "chromium", "node": "nodejs", "npm": "npm", "curl": "curl"}[name] in installed:
                self._provide(name)
        # apt-get records each call (arguments and DEBIAN_FRONTEND); `install` provides what it is asked for
        provide = ""
        if apt_installs:
            provide = (
                'for p in "$@"; do case "$p" in\n'
                f'  espeak-ng) echo "{ESPEAK_LINE}" >> "{self.libs}";;\n'
                f'  chromium) {LN} -sf /bin/true "{self.bin}/chromium";;\n'
                f'  nodejs) {LN} -sf /bin/true "{self.bin}/node";;\n'
                f'  npm) {LN} -sf /bin/true "{self.bin}/npm";;\n'
                f'  curl) {LN} -sf /bin/true "{self.bin}/curl";;\n'
                "esac; done"
            )
        self._tool("apt-get", f'echo "DEBIAN_FRONTEND=${{DEBIAN_FRONTEND:-}} $*" >> "{self.calls}"\n{provide}')

    def _tool(self, name: str, body: str) -> None:
        path = self.bin / name
        path.write_text(f"#!{SH}\n{body}\n")
        path.chmod(0o755)

    def _provide(self, name: str) -> None:
        (self.bin / name).symlink_to("/bin/true")

    def run(self) -> subprocess.CompletedProcess:
        return subprocess.run([SH, str(SCRIPT)], env={"PATH": str(self.bin)}, capture_output=True, text=True,
                              timeout=60)

    def apt_calls(self) -> list[str]:
        return self.calls.read_text().splitlines() if self.calls.exists() else []


@pytest.mark.parametrize("uid", [0, 1000])
def test_nothing_missing_exits_at_once_without_apt(tmp_path, uid):
    system = FakeSystem(tmp_path, uid, {"espeak-ng", "chromium", "nodejs", "npm", "curl"})
    done = system.run()
    assert (done.returncode, done.stdout, done.stderr) == (0, "", "")
    assert system.apt_calls() == []


def test_missing_as_a_normal_user_is_one_line_with_the_install_command(tmp_path):
    system = FakeSystem(tmp_path, 1000, set())
    done = system.run()
    assert done.returncode == 1
    assert done.stdout == ""
    lines = done.stderr.splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith(f"system packages missing: {ALL};")
    assert lines[0].endswith(
        f"sudo sh -c 'apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y {ALL}'")
    assert system.apt_calls() == []


@pytest.mark.parametrize(("installed", "missing"), [
    ({"chromium", "nodejs", "npm", "curl"}, "espeak-ng"),
    ({"espeak-ng", "nodejs", "npm", "curl"}, "chromium"),
    ({"espeak-ng", "chromium", "nodejs", "curl"}, "npm"),
    ({"espeak-ng", "chromium", "curl"}, "nodejs npm"),
    ({"espeak-ng", "chromium", "nodejs", "npm"}, "curl"),
])
def test_the_line_names_only_what_is_missing(tmp_path, installed, missing):
    system = FakeSystem(tmp_path, 1000, installed)
    done = system.run()
    assert done.returncode == 1
    assert done.stderr.splitlines() == [
        f"system packages missing: {missing}; install them with: "
        f"sudo sh -c 'apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y {missing}'"]


def test_missing_as_root_installs_with_apt_then_checks_again(tmp_path):
    system = FakeSystem(tmp_path, 0, {"nodejs", "npm", "curl"})
    done = system.run()
    assert done.returncode == 0, done.stderr
    assert system.apt_calls() == ["DEBIAN_FRONTEND= update -qq",
                                  "DEBIAN_FRONTEND=noninteractive install -y -qq espeak-ng chromium"]
    assert done.stderr.splitlines() == ["installing system packages: espeak-ng chromium"]
    assert system.run().returncode == 0 and len(system.apt_calls()) == 2     # now present: no apt call


def test_root_fails_when_apt_does_not_provide_the_package(tmp_path):
    system = FakeSystem(tmp_path, 0, {"espeak-ng", "nodejs", "npm", "curl"}, apt_installs=False)
    done = system.run()
    assert done.returncode == 1
    assert done.stderr.splitlines()[-1] == \
        "system packages still missing after apt-get install -y chromium: chromium"


# ---- the Makefile and CI call it first -----------------------------------------------------------------------
def make(*args, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(["make", "--no-print-directory", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=60, **kw)


def lines_of(done: subprocess.CompletedProcess) -> list[str]:
    assert done.returncode == 0, done.stderr
    return done.stdout.splitlines()


@pytest.mark.parametrize("target", ["test", "demo", "venv"])
def test_make_runs_the_script_before_building_the_venv_and_before_pytest(target, tmp_path):
    script = "sh scripts/system-deps.sh"
    # -W: as if pyproject.toml had just changed, so the venv would be rebuilt too (VENV in tmp: nothing is touched)
    lines = lines_of(make("-n", "-W", "pyproject.toml", target, f"VENV={tmp_path / 'venv'}"))
    assert lines[0] == script and lines.count(script) == 1
    assert any(" -m venv " in line for line in lines[1:])
    if target == "test":
        assert " -m pytest" in lines[-1]
    # with the venv up to date, the script still runs first
    lines = lines_of(make("-n", target))
    assert lines[0] == script


def test_ci_runs_the_script_and_has_no_apt_of_its_own():
    ci = (REPO / ".ci" / "run").read_text()
    assert "apt-get" not in ci
    commands = [line.strip() for line in ci.splitlines() if line.strip() and not line.startswith("#")]
    assert commands.index("sh scripts/system-deps.sh") < commands.index("make test")


def test_make_test_stops_when_ruff_finds_something(tmp_path):
    """ruff's findings fail `make test` before pytest runs."""
    log = tmp_path / "log"
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    for name, rc in (("python", 0), ("ruff", 1)):
        tool = venv / "bin" / name
        tool.write_text(f'#!{SH}\necho "{name} $*" >> "{log}"\nexit {rc}\n')
        tool.chmod(0o755)
    (venv / ".installed").touch()
    os.utime(venv / ".installed", (2**31, 2**31))
    done = make("test", f"VENV={venv}", f"BLENDER_VENV={venv}", f"SYSTEM_DEPS=echo system-deps >> {log}")
    assert done.returncode != 0
    assert [line.split()[0] for line in log.read_text().splitlines()] == ["system-deps", "ruff"]


@pytest.mark.parametrize(("pytest_rc", "ok"), [(0, True), (5, True), (1, False), (2, False)])
def test_make_test_passes_on_no_tests_collected_and_fails_on_any_other_error(tmp_path, pytest_rc, ok):
    """`make test` for real, with a fake venv whose python records its call and exits with `pytest_rc`."""
    log = tmp_path / "log"
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    python = venv / "bin" / "python"
    python.write_text(f'#!{SH}\necho "pytest $*" >> "{log}"\nexit {pytest_rc}\n')
    python.chmod(0o755)
    ruff = venv / "bin" / "ruff"
    ruff.write_text(f'#!{SH}\necho "ruff $*" >> "{log}"\n')
    ruff.chmod(0o755)
    (venv / ".installed").touch()       # newer than pyproject.toml: no venv build
    os.utime(venv / ".installed", (2**31, 2**31))
    done = make("test", f"VENV={venv}", f"BLENDER_VENV={venv}", f"SYSTEM_DEPS=echo system-deps >> {log}")
    assert log.read_text().splitlines() == ["system-deps", "ruff check visemeflow tests bench examples tools",
                                            "pytest -m pytest -q -n auto --dist loadfile --no-loadscope-reorder --durations=25"]
    assert (done.returncode == 0) is ok, done.stdout + done.stderr
    if pytest_rc == 5:
        assert "pytest: no tests collected" in done.stdout
