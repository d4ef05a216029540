"""The disk cache of compiled C libraries, built so that it heals instead of crashing a later run.

An entry is `<name>_<hash of its source>.so` with `<that>.so.json` beside it (the library's size and sha256),
both renamed into place after an fsync; the record is written after the library, so an entry cut short by a
crash or a full disk lacks it or disagrees with it. Every entry is checked (size, sha256, a dlopen in a child
process) before this process loads it: a library mapped from a truncated file would kill it with SIGBUS. A bad
entry is rebuilt with one warning line; builders of one entry take turns on a lock file; a cache that cannot be
written gives way to a per-run temporary folder with one warning line.
"""

from __future__ import annotations

import atexit
import errno
import fcntl
import hashlib
import json
import logging
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from types import FrameType

log = logging.getLogger(__name__)

CACHE_ENV = "PINNMPC_CACHE"  # where compiled functions are kept (default: ~/.cache/pinnmpc)
CFLAGS = ("-fPIC", "-shared")  # a shared library that ca.external can load
MARCH_ENV = "PINNMPC_MARCH"  # the -march compiled code targets; default native, this host's vector instructions
#   (fused multiply-adds, AVX), each entry keyed to the host's CPU; empty: the compiler's default target, code
#   that any machine of the architecture runs, for a cache shared between machines (docs/design.md)
BUILD_PREFIX = ".build-"  # a build folder in the cache: .build-<pid>-<host tag>-<random>
LEGACY_BUILD = re.compile(r"tmp[a-z0-9_]{8}")  # build folders of older pinnmpc versions (tempfile names)
STALE_AFTER_S = 3600.0  # a build folder this old whose owner cannot be checked is an orphan
STDERR_LINES = 3  # of a failed compile's stderr, in its one-line error
MISSING = "missing"
PROBE = "import ctypes, sys; ctypes.CDLL(sys.argv[1])"  # dlopen, in a child that may die of it instead of us
HOW = f"set {CACHE_ENV} to a writable folder to keep compiled code"
HOST = hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]  # pids mean something on this host only

_ready: dict[tuple[Path | None, str], Path] = {}  # (cache folder, key) -> a library checked by this process
_swept: set[Path] = set()  # cache folders whose orphans this process has removed
_unwritable: dict[Path, str] = {}  # cache folder -> why it cannot be written (warned once)
_fallback: list[Path] = []  # this run's temporary cache, once made


class CompileError(RuntimeError, ValueError):
    """A library that cannot be built or loaded, in one line: a RuntimeError for callers that do without compiled
    code (bench rows), a ValueError so a job reports it as one line and exit 2, not a traceback."""


def cache_dir() -> Path | None:
    """Folder of compiled libraries, keyed by the hash of their C source: $PINNMPC_CACHE or ~/.cache/pinnmpc
    (None without either: no HOME and no passwd entry)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]).expanduser()
    try:
        return Path.home() / ".cache" / "pinnmpc"
    except RuntimeError:
        return None


def entry_key(name: str, source: str, opt: str) -> str:
    """An entry's file stem: the same C at the same optimisation level for the same target is the same library."""
    target = " ".join(march_flags()) + (f" {cpu_tag()}" if march() == "native" else "")
    return f"{name}_{hashlib.sha256((source + opt + target).encode()).hexdigest()[:16]}"


def march() -> str:
    """The -march compiled code targets ($PINNMPC_MARCH, default native)."""
    return os.environ.get(MARCH_ENV, "native").strip()


def march_flags() -> tuple[str, ...]:
    """The compiler flags for march() (none where it is empty: the compiler's default target)."""
    return (f"-march={march()}",) if march() else ()


def cpu_tag() -> str:
    """This host's CPU (model and feature flags): code built for one CPU's native target may not run on another."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        import platform

        lines = [platform.machine(), platform.processor()]
    wanted = [line for line in lines if line.split(":")[0].strip() in ("model name", "flags", "Features")][:2]
    return hashlib.sha256("\n".join(wanted or lines[:1]).encode()).hexdigest()[:12]


def record_path(lib: Path) -> Path:
    """The size-and-checksum record beside a library."""
    return lib.with_name(lib.name + ".json")


def library(name: str, source: str, opt: str) -> Path:
    """A checked library compiled from source at opt: from the cache, or built (again, if bad) and cached."""
    key, directory = entry_key(name, source, opt), cache_dir()
    if (directory, key) not in _ready:
        if directory is None:
            lib = _for_this_run(name, source, opt, key, "there is no home folder for a compiled cache")
        else:
            lib = _cached(name, source, opt, key, directory)
        _ready[directory, key] = lib
    return _ready[directory, key]


def _cached(name: str, source: str, opt: str, key: str, directory: Path) -> Path:
    """The entry in the cache folder, rebuilt there if bad; built for this run only where the folder is read-only."""
    _sweep(directory)
    lib = directory / f"{key}.so"
    problem = check(lib)
    if problem is None:
        return lib
    if directory not in _unwritable:
        try:
            with _entry_lock(directory, key):
                problem = check(lib)  # a concurrent builder may have just finished it
                if problem is not None:
                    if problem != MISSING:
                        log.warning("compiled cache entry %s is bad (%s): rebuilding it", lib, problem)
                    if lib.is_dir() and not lib.is_symlink():
                        shutil.rmtree(lib)  # a folder by an entry's name is in the way of the rename
                    _build(name, source, opt, lib)
                    _built(name, lib)
                return lib
        except OSError as e:
            _unwritable[directory] = _why_unwritable(directory, e)
    bad = f"compiled cache entry {lib} is bad ({problem}) and " if problem != MISSING else ""
    why = f"{bad}compiled cache {directory} cannot be written ({_unwritable[directory]})"
    return _for_this_run(name, source, opt, key, why, warn=bool(bad))


def _for_this_run(name: str, source: str, opt: str, key: str, why: str, warn: bool = False) -> Path:
    """The library built in this run's temporary folder (removed at exit); why is warned the first time, or
    with warn (a bad entry of the cache)."""
    lib = _fallback_dir(why, warn) / f"{key}.so"
    if check(lib) is not None:
        _build(name, source, opt, lib)
        _built(name, lib)
    return lib


def _built(name: str, lib: Path) -> None:
    """Refuse a library just built that does not check out (one line, not a crash when it is loaded)."""
    problem = check(lib)
    if problem is not None:
        raise CompileError(f"compiling {name}: the library just built at {lib} is bad ({problem})")


def check(lib: Path) -> str | None:
    """None for a sound entry, MISSING for none, else why it is bad (checked before anything maps it)."""
    try:
        if not lib.exists():
            return MISSING
        if not lib.is_file():
            return "not a file"
        size = lib.stat().st_size
        try:
            record = json.loads(record_path(lib).read_text())
        except FileNotFoundError:
            return f"no size-and-checksum record {record_path(lib).name} beside it"
        except (ValueError, UnicodeDecodeError):
            return f"its record {record_path(lib).name} is unreadable"
        if not isinstance(record, dict) or not isinstance(record.get("size"), int) or "sha256" not in record:
            return f"its record {record_path(lib).name} is unreadable"
        if size != record["size"]:
            return f"{size} bytes, its record says {record['size']}" + (" (cut short)" if size < record["size"] else "")
        if _sha256(lib) != record["sha256"]:
            return "its bytes differ from the sha256 in its record"
    except OSError as e:
        return f"unreadable: {e.strerror or e}"
    return _probe(lib)


def _probe(lib: Path) -> str | None:
    """None if a child process can dlopen the library (a truncated or foreign one kills or fails the child)."""
    if not sys.executable:
        return None
    try:
        done = subprocess.run(
            [sys.executable, "-I", "-S", "-c", PROBE, str(lib)], capture_output=True, text=True, timeout=120
        )
    except (OSError, subprocess.TimeoutExpired):
        return None  # no child to try it in: the checksum has to do
    if done.returncode == 0:
        return None
    if done.returncode < 0:
        return f"loading it killed a test process with {signal.Signals(-done.returncode).name}"
    lines = done.stderr.strip().splitlines()
    return f"it does not load: {lines[-1] if lines else f'exit {done.returncode}'}"


def _sha256(path: Path) -> str:
    """The file's sha256, read in blocks (generated libraries of large arms run to megabytes)."""
    h = hashlib.sha256()
    with path.open("rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
    return h.hexdigest()


def _build(name: str, source: str, opt: str, lib: Path) -> None:
    """Compile source into a build folder beside lib, then publish the library and its record atomically."""
    compiler = find_compiler(name)
    build = Path(tempfile.mkdtemp(prefix=f"{BUILD_PREFIX}{os.getpid()}-{HOST}-", dir=lib.parent))
    try:
        src = build / f"{name}.c"
        src.write_text(source)
        out = build / lib.name
        # a large arm's generated code is slow to compile: say what the wait is (once; the library is cached)
        flags = " ".join((opt, *march_flags()))
        print(f"compiling {name} ({len(source) // 1024} kB of C, {flags}) into {lib.parent}", file=sys.stderr)
        run_compiler([compiler, opt, *march_flags(), *CFLAGS, str(src), "-o", str(out), "-lm"], name, src)
        publish(out, lib)
    except CompileError:
        raise  # the build folder keeps the source the message names; a later run removes it
    except BaseException:
        shutil.rmtree(build, ignore_errors=True)
        raise
    shutil.rmtree(build, ignore_errors=True)


def find_compiler(name: str) -> str:
    """The C compiler: $CC, else cc or gcc on PATH."""
    compiler = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc")
    if compiler is None:
        raise CompileError(f"no C compiler found (CC={os.environ.get('CC', 'cc')}); install gcc to compile {name}")
    return compiler


def run_compiler(cmd: list[str], name: str, src: Path) -> None:
    """Run the compiler in its own process group, killed with all its children if this process is interrupted
    (an orphaned compile would keep a core busy and its folder in the cache)."""
    with _sigterm_raises() as arm:
        try:
            proc = subprocess.Popen(
                cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True
            )
        except OSError as e:
            raise CompileError(f"compiling {name} failed: {cmd[0]} cannot run ({e.strerror or e})") from None
        try:
            arm()  # a SIGTERM held while the compiler started raises here, where the compiler is known and killed
            _, err = proc.communicate()
        finally:
            if proc.poll() is None:
                with suppress(OSError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    if proc.returncode != 0:
        lines = [s.strip() for s in err.decode(errors="replace").splitlines() if s.strip()][-STDERR_LINES:]
        how = f"signal {-proc.returncode}" if proc.returncode < 0 else f"exit {proc.returncode}"
        said = " | ".join(lines)[-600:] if lines else "nothing on stderr"
        raise CompileError(f"compiling {name} failed: {cmd[0]} on {src} ({how}): {said}")


@contextmanager
def _sigterm_raises() -> Iterator[Callable[[], None]]:
    """While compiling, a SIGTERM that would kill this process outright raises instead, so the compiler dies too.
    One that comes before the compiler's process is known (inside Popen: the compiler may already run) is held until
    the caller arms the handler with the function this yields, and raises then; held to the end, it raises there."""
    held: list[int] = []
    armed = [False]

    def stop(signum: int, _frame: FrameType | None) -> None:
        if not armed[0]:
            held.append(signum)
            return
        raise SystemExit(128 + signum)

    def arm() -> None:
        armed[0] = True
        if held:
            raise SystemExit(128 + held[0])

    installed = False
    if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:  # a handler of the caller's (the CLI's) stays
        try:
            signal.signal(signal.SIGTERM, stop)
            installed = True
        except ValueError:  # not the main thread: signals are not ours to take
            pass
    try:
        yield arm
    finally:
        if installed:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
        if held and not armed[0]:  # the compiler never started (or failed to): the signal still ends this process
            raise SystemExit(128 + held[0])


def publish(built: Path, lib: Path) -> None:
    """Rename a built library into place, then its record: each fsynced, file and folder, so a crash leaves
    the old entry, no entry, or a library its record does not vouch for (rebuilt), never a vouched-for stub."""
    record = {"size": built.stat().st_size, "sha256": _sha256(built), "built": time.strftime("%Y-%m-%dT%H:%M:%S")}
    _fsync(built)
    os.replace(built, lib)
    _fsync(lib.parent)
    staged = built.with_name(built.name + ".json")
    staged.write_text(json.dumps(record) + "\n")
    _fsync(staged)
    os.replace(staged, record_path(lib))
    _fsync(lib.parent)


def _fsync(path: Path) -> None:
    """Flush a file's or a folder's contents to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError as e:
        if e.errno not in (errno.EINVAL, errno.EBADF):  # a file system that cannot sync folders
            raise
    finally:
        os.close(fd)


@contextmanager
def _entry_lock(directory: Path, key: str) -> Iterator[None]:
    """One builder of an entry at a time (released by the kernel if the holder dies); OSError where the
    cache cannot be written."""
    directory.mkdir(parents=True, exist_ok=True)
    fd = os.open(directory / f"{key}.lock", os.O_RDONLY | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            print(f"waiting for another process compiling {key} in {directory}", file=sys.stderr)
            fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError:
            pass  # a file system without locks: the atomic renames still keep entries whole
        yield
    finally:
        os.close(fd)


def _why_unwritable(directory: Path, e: OSError) -> str:
    """Why a cache folder cannot take entries, in words."""
    for p in (directory, *directory.parents):
        if p.exists() and not p.is_dir():
            return f"{p} is a file"
    return e.strerror or str(e)


def _fallback_dir(why: str, warn: bool) -> Path:
    """This run's temporary cache (removed at exit), made with one warning line the first time it is needed."""
    if not _fallback:
        try:
            tmp = Path(tempfile.mkdtemp(prefix="pinnmpc-cache-"))
        except OSError as e:
            raise CompileError(f"{why}, nor can a temporary folder ({e.strerror or e}); {HOW}") from None
        atexit.register(shutil.rmtree, tmp, True)
        _fallback.append(tmp)
        warn = True
    if warn:
        log.warning("%s: compiling into %s for this run only; %s", why, _fallback[0], HOW)
    return _fallback[0]


def _sweep(directory: Path) -> None:
    """Remove build folders of compiles that were killed: this host's whose process is gone, other hosts' and
    older pinnmpc's once older than STALE_AFTER_S (a live builder's folder is kept)."""
    if directory in _swept:
        return
    _swept.add(directory)
    try:
        entries = [e for e in directory.iterdir() if e.is_dir()]
    except OSError:
        return
    now = time.time()
    for e in entries:
        parts = e.name[len(BUILD_PREFIX) :].split("-") if e.name.startswith(BUILD_PREFIX) else None
        if parts is None and not LEGACY_BUILD.fullmatch(e.name):
            continue
        if parts is not None and len(parts) >= 2 and parts[0].isdigit() and parts[1] == HOST:
            orphan = int(parts[0]) != os.getpid() and not _alive(int(parts[0]))
        else:  # another host's, or an older pinnmpc's: only its age tells
            try:
                orphan = now - e.stat().st_mtime > STALE_AFTER_S
            except OSError:
                continue
        if orphan:
            shutil.rmtree(e, ignore_errors=True)


def _alive(pid: int) -> bool:
    """Whether a process of this host has that pid."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # someone else's process
    return True
