"""The compiled cache heals (pinnmpc.systems.cache): every state a cache can be found in ends in a clean run with
the right numbers or in one error line and a non-zero exit. Real processes, real compiles of a tiny CasADi
function: one fresh Python imports pinnmpc once and forks a process per cache state (a SIGBUS kills that
process only, and shows in its exit status)."""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from pinnmpc.systems import cache

ROOT = Path(__file__).resolve().parents[1]
NAME = "cachetest_tiny"
EXPECTED = [math.sin(0.5) * 3.0, 0.5 + 2 * 3.0]
BODY = f"""
import json, os, sys, tempfile
import casadi as ca
from pinnmpc.cli import run_cli
from pinnmpc.systems.compiled import compile_functions

def body():
    x = ca.SX.sym("x", 2)
    f = ca.Function("{NAME}", [x], [ca.vertcat(ca.sin(x[0]) * x[1], x[0] + 2 * x[1])])
    return compile_functions("{NAME}", [f])["{NAME}"]([0.5, 3.0]).full().ravel().tolist()
"""
CHILD = BODY + 'print(json.dumps(run_cli(body, "pinnmpc.cachetest")))\n'
RUNNER = (
    BODY
    + """
for case in json.loads(sys.argv[1]):  # one forked process per cache state, its env, stdout and stderr its own
    pid = os.fork()
    if pid == 0:
        for fd, name in ((1, "stdout"), (2, "stderr")):
            os.dup2(os.open(case[name], os.O_WRONLY | os.O_CREAT | os.O_TRUNC), fd)
        for k, v in case["env"].items():
            os.environ.pop(k, None) if v is None else os.environ.__setitem__(k, v)
        tempfile.tempdir = None
        print(json.dumps(run_cli(body, "pinnmpc.cachetest")))
        sys.exit(0)
    with open(case["status"], "w") as f:
        f.write(str(os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])))
"""
)
FAILING_CC = "#!/bin/sh\necho 'tiny.c:1:1: error: expected something' >&2\necho 'compilation terminated.' >&2\nexit 1\n"


@dataclass
class Run:
    """What one process did: exit code (-signal if killed), stdout, stderr."""

    returncode: int
    stdout: str
    stderr: str

    @property
    def compiles(self) -> list[str]:
        """Its compile announcements."""
        return [s for s in self.stderr.splitlines() if s.startswith("compiling ")]

    @property
    def said(self) -> list[str]:
        """Every other non-empty stderr line."""
        return [s for s in self.stderr.splitlines() if s.strip() and not s.startswith("compiling ")]


def child_env(base: Path, **env: str | None) -> dict[str, str | None]:
    """A case's own cache, HOME and TMPDIR under base (None: the variable is unset)."""
    for d in ("home", "tmp"):
        (base / d).mkdir(parents=True, exist_ok=True)
    own = {"HOME": str(base / "home"), cache.CACHE_ENV: str(base / "cache"), "TMPDIR": str(base / "tmp")}
    return {**own, "HYDRA_FULL_ERROR": None, "PINNMPC_VERBOSE": None, **env}


def full_env(env: dict[str, str | None]) -> dict[str, str]:
    """os.environ with a case's changes, for a fresh process."""
    out = {**os.environ, "PYTHONPATH": str(ROOT)}
    for k, v in env.items():
        if v is None:
            out.pop(k, None)
        else:
            out[k] = v
    return out


def run_child(env: dict[str, str | None]) -> Run:
    """The tiny function compiled (or loaded) and evaluated in a fresh Python process."""
    r = subprocess.run([sys.executable, "-c", CHILD], env=full_env(env), cwd=ROOT, capture_output=True, text=True)
    return Run(r.returncode, r.stdout, r.stderr)


def assert_clean_or_one_line(r: Run) -> None:
    """The invariant over every cache state: the right numbers, or one error line and a non-zero exit."""
    assert "Traceback" not in r.stderr, r.stderr
    if r.returncode == 0:
        assert json.loads(r.stdout.strip().splitlines()[-1]) == pytest.approx(EXPECTED, rel=1e-12)
    else:
        assert r.returncode > 0, f"killed by signal {-r.returncode}: {r.stderr}"
        assert len(r.said) == 1, r.stderr


def entry(directory: Path) -> Path:
    """The one cached library of the tiny function in a cache folder."""
    (lib,) = directory.glob(f"{NAME}_*.so")
    return lib


def copy_entry(sound: Path, to: Path) -> Path:
    """The sound entry (library and record) copied into a fresh cache folder; its library's path there."""
    to.mkdir(parents=True)
    lib = entry(sound)
    for p in (lib, cache.record_path(lib)):
        shutil.copy2(p, to / p.name)
    return to / lib.name


def truncated(lib: Path) -> None:
    """Cut short past its headers, as a killed writer or a full disk leaves it (dlopen of it dies of SIGBUS)."""
    os.truncate(lib, lib.stat().st_size * 2 // 5)


def garbage(lib: Path) -> None:
    """The same size, other bytes."""
    lib.write_bytes(os.urandom(lib.stat().st_size))


def vouch(lib: Path, corrupt: Callable[[Path], None]) -> None:
    """Corrupt the library and write a record that matches it: what a dlopen in a child still catches."""
    corrupt(lib)
    record = {"size": lib.stat().st_size, "sha256": hashlib.sha256(lib.read_bytes()).hexdigest()}
    cache.record_path(lib).write_text(json.dumps(record))


CORRUPTIONS: dict[str, tuple[Callable[[Path], object], str]] = {  # how an entry goes bad, what its warning says
    "empty": (lambda lib: lib.write_bytes(b""), "(cut short)"),
    "truncated": (truncated, "(cut short)"),
    "garbage": (garbage, "its bytes differ from the sha256 in its record"),
    "garbage_no_record": (lambda lib: (garbage(lib), cache.record_path(lib).unlink()), "no size-and-checksum record"),
    "no_record": (lambda lib: cache.record_path(lib).unlink(), "no size-and-checksum record"),
    "record_garbage": (lambda lib: cache.record_path(lib).write_bytes(b"\xff{"), "is unreadable"),
    "record_lies": (lambda lib: cache.record_path(lib).write_text('{"size": 1, "sha256": "0"}'), "its record says 1"),
    "folder": (lambda lib: (lib.unlink(), lib.mkdir()), "not a file"),
    "vouched_garbage": (lambda lib: vouch(lib, garbage), "it does not load"),  # the record cannot tell
    "vouched_truncated": (lambda lib: vouch(lib, truncated), "killed a test process with SIGBUS"),
}
UNWRITABLE = ["readonly_missing", "readonly_sound", "readonly_truncated", "cache_is_file", "under_a_file", "home"]
ORPHANS = {  # folder in the cache -> whether a run removes it (the part after the last "-" tells them apart)
    f"{cache.BUILD_PREFIX}DEAD-{cache.HOST}-dead": True,  # this host's, its process gone
    f"{cache.BUILD_PREFIX}{os.getpid()}-{cache.HOST}-live": False,  # a live builder's
    f"{cache.BUILD_PREFIX}DEAD-otherhst-other": False,  # another host's, recent
    "tmpabcd1234": True,  # an older pinnmpc's, old
    "tmpefgh5678": False,  # an older pinnmpc's, recent
    "keepme": False,  # not a build folder
}


def readonly_prefix(paths: list[Path]) -> list[str] | None:
    """A command prefix under which paths are read-only, even for root (read-only bind mounts); None if root
    cannot make one here."""
    if os.geteuid() != 0:
        for p in paths:
            p.chmod(0o555)
        return []
    mounts = " && ".join(f'mount --bind -o ro "{p}" "{p}"' for p in paths)
    prefix = ["unshare", "-m", "sh", "-c", f'{mounts} && exec "$@"', "sh"]
    if shutil.which("unshare") is None or subprocess.run([*prefix, "true"], capture_output=True).returncode != 0:
        return None
    return prefix


def setup_case(case: str, base: Path, sound: Path) -> tuple[dict[str, str | None], Path | None]:
    """A cache in the given state under base: the case's env, and a folder it must leave as it was (or None)."""
    env, folder = child_env(base), base / "cache"
    if case in CORRUPTIONS:
        CORRUPTIONS[case][0](copy_entry(sound, folder))
    elif case == "sound":
        copy_entry(sound, folder)
    elif case.startswith("readonly"):
        folder.mkdir()
        if case != "readonly_missing":
            lib = copy_entry(sound, base / "other")
            if case == "readonly_truncated":
                truncated(lib)
            for p in (lib, cache.record_path(lib)):
                shutil.move(p, folder / p.name)
        return env, folder
    elif case in ("cache_is_file", "under_a_file"):
        folder.write_text("not a folder")
        if case == "under_a_file":
            env[cache.CACHE_ENV] = str(folder / "pinnmpc")
        return env, None
    elif case == "home":
        env[cache.CACHE_ENV] = None
        return env, base / "home"
    elif case == "compiler_fails":
        (base / "badcc").write_text(FAILING_CC)
        (base / "badcc").chmod(0o755)
        env["CC"] = str(base / "badcc")
    elif case == "no_compiler":
        env.update(CC="/nonexistent/cc", PATH=str(base))
    elif case == "orphans":
        dead = subprocess.Popen(["true"])
        dead.wait()
        for name in ORPHANS:
            (folder / name.replace("DEAD", str(dead.pid))).mkdir(parents=True)
        old = time.time() - 2 * cache.STALE_AFTER_S
        os.utime(folder / "tmpabcd1234", (old, old))
    return env, None


CASES = ["missing", "sound", *CORRUPTIONS, *UNWRITABLE, "compiler_fails", "no_compiler", "orphans"]


@pytest.fixture(scope="module")
def sound(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A cache folder holding the tiny function's entry, built by a real compile from an empty cache."""
    base = tmp_path_factory.mktemp("sound")
    r = run_child(child_env(base))
    assert_clean_or_one_line(r)
    assert r.returncode == 0 and len(r.compiles) == 1 and not r.said, r.stderr
    assert cache.check(entry(base / "cache")) is None
    return base / "cache"


@pytest.fixture(scope="module")
def fuzz(tmp_path_factory: pytest.TempPathFactory, sound: Path) -> dict[str, tuple[Run, Path, list[str] | None]]:
    """Every case run: (what its process did, its base folder, the listing of its read-only folder before)."""
    root, cases, readonly, before = tmp_path_factory.mktemp("fuzz"), [], [], {}
    for case in CASES:
        base = root / case
        env, frozen = setup_case(case, base, sound)
        if frozen is not None:
            readonly.append(frozen)
            before[case] = sorted(p.name for p in frozen.iterdir())
        files = {k: str(base / k) for k in ("stdout", "stderr", "status")}
        cases.append({"env": env, **files})
    prefix = readonly_prefix(readonly)
    if prefix is None:  # root without unshare -m: the read-only states are left out (and their tests skipped)
        keep = [c not in before for c in CASES]
        cases, prefix = [c for c, k in zip(cases, keep) if k], []
    subprocess.run([*prefix, sys.executable, "-c", RUNNER, json.dumps(cases)], env=full_env({}), cwd=ROOT, check=True)
    out = {}
    for case in CASES:
        if not (root / case / "status").is_file():
            continue  # left out above
        base = root / case
        status, stdout, stderr = ((base / k).read_text() for k in ("status", "stdout", "stderr"))
        out[case] = (Run(int(status), stdout, stderr), base, before.get(case))
    return out


@pytest.mark.parametrize("case", CASES)
def test_every_cache_state_ends_in_a_clean_run_or_one_line(fuzz, case: str) -> None:
    if case not in fuzz:
        pytest.skip("root without a way to make a read-only folder (unshare -m)")
    run, base, _ = fuzz[case]
    assert_clean_or_one_line(run)
    assert not list((base / "tmp").iterdir())  # nothing left in the temporary folder


@pytest.mark.parametrize("case", sorted(CORRUPTIONS))
def test_a_bad_entry_is_rebuilt_with_one_line_naming_it(fuzz, case: str) -> None:
    run, base, _ = fuzz[case]
    lib = entry(base / "cache")
    assert run.returncode == 0 and len(run.compiles) == 1, run.stderr
    (line,) = run.said
    assert str(lib) in line and CORRUPTIONS[case][1] in line and "rebuilding it" in line, line
    assert cache.check(lib) is None  # healed: the next run loads it without a word


def test_a_sound_entry_is_loaded_and_a_missing_one_built_without_a_word(fuzz) -> None:
    for case, compiles in (("sound", 0), ("missing", 1)):
        run, base, _ = fuzz[case]
        assert run.returncode == 0 and len(run.compiles) == compiles and not run.said, run.stderr
        assert cache.check(entry(base / "cache")) is None


@pytest.mark.parametrize("case", UNWRITABLE)
def test_a_cache_that_cannot_be_written_gives_way_to_a_run_folder(fuzz, case: str) -> None:
    if case not in fuzz:
        pytest.skip("root without a way to make a read-only folder (unshare -m)")
    run, base, before = fuzz[case]
    assert run.returncode == 0, run.stderr
    if case == "readonly_sound":
        assert not run.compiles and not run.said, run.stderr  # a sound entry of a read-only cache is used as it is
    else:
        assert len(run.compiles) == 1, run.stderr
        (line,) = run.said
        assert "cannot be written" in line and "for this run only" in line, line
        assert ("is bad" in line) == (case == "readonly_truncated"), line
        assert ("is a file" in line) == (case in ("cache_is_file", "under_a_file")), line
    if before is not None:
        assert sorted(p.name for p in (base / ("home" if case == "home" else "cache")).iterdir()) == before


def test_a_failing_compiler_is_one_line_naming_it_its_source_and_its_errors(fuzz) -> None:
    run, base, _ = fuzz["compiler_fails"]
    (line,) = run.said
    start = f"pinnmpc.cachetest: error: compiling {NAME} failed: {base / 'badcc'} on {base / 'cache'}/"
    assert run.returncode == 2 and line.startswith(start), line
    assert f"{NAME}.c (exit 1): tiny.c:1:1: error: expected something | compilation terminated." in line, line
    assert not list((base / "cache").glob("*.so"))


def test_no_compiler_is_one_line(fuzz) -> None:
    run, _, _ = fuzz["no_compiler"]
    assert run.returncode == 2 and "error: no C compiler found (CC=/nonexistent/cc)" in run.said[0], run.stderr


def test_build_folders_of_killed_compiles_are_swept_and_live_ones_kept(fuzz) -> None:
    run, base, _ = fuzz["orphans"]
    assert run.returncode == 0, run.stderr
    left = {p.name.rsplit("-", 1)[-1] for p in (base / "cache").iterdir() if p.is_dir()}
    assert left == {name.rsplit("-", 1)[-1] for name, removed in ORPHANS.items() if not removed}


def test_a_truncated_entry_kills_a_plain_load_but_not_a_run(sound: Path, tmp_path: Path) -> None:
    lib = copy_entry(sound, tmp_path / "cache")
    truncated(lib)
    plain = f"import casadi as ca; ca.external('{NAME}', '{lib}')([0.5, 3.0])"
    crash = subprocess.run([sys.executable, "-c", plain], capture_output=True, timeout=60)
    assert crash.returncode == -signal.SIGBUS  # what every run did before entries were checked
    r = run_child(child_env(tmp_path))
    assert_clean_or_one_line(r)
    assert r.returncode == 0 and len(r.said) == 1 and "cut short" in r.said[0], r.stderr


def test_concurrent_builders_of_one_entry_compile_it_once(tmp_path: Path) -> None:
    env = full_env(child_env(tmp_path))
    procs = [
        subprocess.Popen([sys.executable, "-c", CHILD], env=env, cwd=ROOT, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
        for _ in range(2)
    ]  # fmt: skip
    done = [Run(p.wait(120), *p.communicate()) for p in procs]
    for r in done:
        assert_clean_or_one_line(r)
        assert r.returncode == 0 and all(s.startswith("waiting for another process") for s in r.said), r.stderr
    assert sum(len(r.compiles) for r in done) == 1
    assert cache.check(entry(tmp_path / "cache")) is None


def _process(pid: int) -> tuple[str, str] | None:
    """(state, start time) of a process from /proc/<pid>/stat (None: no such process)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(") ", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return None
    return fields[0], fields[19]  # state, starttime (clock ticks since boot)


def _wait_until(condition: Callable[[], bool], bound: float) -> bool:
    """Poll until condition() holds or the bound (s) passes; whether it held. The bound only guards against a hang:
    a loaded machine may take its time."""
    deadline = time.monotonic() + bound
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.05)
    return condition()


@pytest.mark.parametrize("when", ["as it starts", "at once", "inside the compile"])
def test_an_interrupted_compile_kills_the_compiler_and_its_folder(tmp_path: Path, when: str) -> None:
    pidfile, cc = tmp_path / "compiler.pid", tmp_path / "slowcc"
    # "as it starts": the compiler signals its parent itself, which may still be starting it (inside Popen)
    own = "kill -TERM $PPID\n" if when == "as it starts" else ""
    cc.write_text(f"#!/bin/sh\nsleep 600 &\necho $! > {pidfile}.tmp\nmv {pidfile}.tmp {pidfile}\n{own}wait\n")
    cc.chmod(0o755)
    env = full_env(child_env(tmp_path, CC=str(cc)))
    proc = subprocess.Popen([sys.executable, "-c", CHILD], env=env, cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert _wait_until(pidfile.is_file, 300), "the compiler never started"
        compiler = int(pidfile.read_text())
        started = _process(compiler)
        assert started is not None
        if when != "as it starts":
            time.sleep(0.5 if when == "inside the compile" else 0.0)
            proc.send_signal(signal.SIGTERM)
        assert proc.wait(300) == 128 + signal.SIGTERM
    finally:
        proc.kill()
        proc.communicate()

    def gone() -> bool:
        """The compiler is dead: no such process, a zombie, or its pid taken by a process started later."""
        now = _process(compiler)
        return now is None or now[0] in ("Z", "X") or now[1] != started[1]

    assert _wait_until(gone, 120), "the compiler lives on"
    assert not [p for p in (tmp_path / "cache").iterdir() if p.is_dir()]  # its build folder went with it


@pytest.mark.parametrize("armed", [True, False])
def test_a_sigterm_while_the_compiler_starts_is_held_until_it_can_be_killed(armed: bool) -> None:
    """Inside Popen the compiler may already run but its process is not known yet: a SIGTERM there is held, and
    raised where the compiler is known (arm()), or at the end where it never started."""
    lines = [
        "import os, signal",
        "from pinnmpc.systems.cache import _sigterm_raises",
        "with _sigterm_raises() as arm:",
        "    os.kill(os.getpid(), signal.SIGTERM)",  # as if inside Popen
        "    print('held', flush=True)",
        *(["    arm()"] if armed else []),
        "    print('after arm', flush=True)",
        "print('after the compile', flush=True)",
    ]
    body = "\n".join(lines) + "\n"
    r = subprocess.run([sys.executable, "-c", body], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 128 + signal.SIGTERM, r.stderr[-2000:]
    assert r.stdout.split() == (["held"] if armed else ["held", "after", "arm"]), r.stdout


def test_each_target_has_its_own_entry_and_the_default_is_this_hosts_cpu(tmp_path: Path) -> None:
    native, portable = (run_child(child_env(tmp_path, **{cache.MARCH_ENV: m})) for m in (None, ""))
    for r in (native, portable):
        assert r.returncode == 0 and json.loads(r.stdout.splitlines()[-1]) == pytest.approx(EXPECTED), r.stderr
    assert "-march=native" in native.stderr and "-march" not in portable.stderr  # the compile line says it
    assert len(list((tmp_path / "cache").glob(f"{NAME}_*.so"))) == 2
