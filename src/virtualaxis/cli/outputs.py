"""Safe outputs for CLI commands: paths checked before the work starts, files written under a temporary name
in the same folder and renamed when complete, nothing overwritten without ``--force``.

A command calls :func:`check_output_file` / :func:`check_output_dir` for every output right after parsing its
inputs (so a bad ``--out`` is reported in a second, not after an hour of simulation), then writes through
:func:`atomic_path` (a temporary sibling, ``os.replace`` onto the final name on success, removed on any error,
``KeyboardInterrupt`` included; SIGTERM is turned into one by :mod:`virtualaxis.cli.main`) or
:func:`staged_dir` (a temporary sub-folder whose files are moved into place on success). A final path
therefore either holds a complete output or is untouched.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from virtualaxis.cli.errors import CliError, StdoutError

#: virtual file systems no output may go to
_FORBIDDEN_ROOTS = ("/proc", "/sys", "/dev")


def add_force_argument(p) -> None:
    """``--force``: allow replacing existing outputs."""
    p.add_argument("--force", action="store_true", help="overwrite existing output files")


def _forbidden(path: Path) -> bool:
    s = str(path.resolve())
    return any(s == root or s.startswith(root + "/") for root in _FORBIDDEN_ROOTS)


#: bytes a temporary sibling adds to a file name (``.`` + ``.partial-`` + 8 random characters)
_TMP_NAME_EXTRA = 18
#: outputs claimed by the running command: resolved path -> option (two outputs must not be one path)
_CLAIMED: dict[str, str] = {}


def reset_claims() -> None:
    """Forget the outputs of the previous command (``main`` calls it for each command)."""
    _CLAIMED.clear()


def _claim(p: Path, option: str) -> None:
    key = os.path.abspath(os.path.expanduser(str(p)))
    try:
        key = str(Path(key).resolve())
    except OSError:
        pass
    other = _CLAIMED.get(key)
    if other is not None and other != option:
        raise CliError(f"{option}: {p} is also the output of {other}; give each output its own path")
    _CLAIMED[key] = option


def claim_output(path: str | Path, option: str) -> None:
    """Record ``path`` as the output of ``option`` (for outputs checked by the command itself): another output
    of the same command naming the same file is then refused by :func:`check_output_file`."""
    _claim(Path(path), option)


def _check_spelling(path: str | Path, option: str) -> None:
    """Paths the shell would have meant otherwise: an unexpanded ``~`` (quoted), an empty path."""
    s = str(path)
    if s.strip() == "":
        raise CliError(f"{option}: empty path")
    if s.startswith("~"):
        raise CliError(f"{option}: {s} starts with '~', which the shell did not expand (quoted?); "
                       "write the full path or $HOME/...")
    for part in Path(s).parts:  # before any stat(): a name over NAME_MAX makes even exists() raise
        n = len(os.fsencode(part))
        if n > 255:
            raise CliError(f"{option}: name {part[:24]}... is {n} bytes long; file systems take at most 255 bytes "
                           "per name")


def _os_errors_named(fn):
    """Any OS error while checking a path (a name too long, a loop of symbolic links, no permission to look)
    becomes one line naming the option and the path, not an internal error."""
    import functools

    @functools.wraps(fn)
    def wrapper(path, *args, **kwargs):
        try:
            return fn(path, *args, **kwargs)
        except (OSError, RuntimeError) as exc:  # (pathlib's resolve() raises RuntimeError on a symlink loop)
            option = kwargs.get("option") or next((a for a in args if isinstance(a, str) and a.startswith("--")),
                                                  "--out")
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else " ".join(str(exc).split())
            raise CliError(f"{option}: {path}: {why}") from None

    return wrapper


def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError):
        return 255


def _probe_folder(folder: Path, option: str, leaf: str | None = None) -> None:
    """Prove that ``folder`` can be created (if missing) and a file (``leaf``, via its temporary sibling) can be
    created in it, without leaving anything behind: a refused command leaves no empty folder."""
    if _forbidden(folder):
        raise CliError(f"{option}: {folder}: not a place for output files (a virtual file system)")
    missing: list[str] = []
    anc = folder
    for anc in [folder, *folder.parents]:
        if anc.exists():
            if not anc.is_dir():
                raise CliError(f"{option}: {anc} is a file, not a folder")
            break
        missing.append(anc.name)
    limit = _name_max(anc)
    for name in [*missing, *([leaf] if leaf else [])]:
        extra = _TMP_NAME_EXTRA if name == leaf else 0
        n = len(os.fsencode(name))
        if n + extra > limit:
            raise CliError(f"{option}: name {name[:24]}... is {n} bytes long; the file system takes {limit} bytes "
                           f"per name{f' ({limit - extra} with the temporary name of the write)' if extra else ''}")
    try:
        fd, probe = tempfile.mkstemp(prefix=".virtualaxis-probe-", dir=anc)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise CliError(f"{option}: cannot write in {anc} ({exc.strerror or exc})") from None


def check_input_file(path: str | Path, option: str) -> Path:
    """An input file must exist, be a file (not a folder) and be readable; checked before any work."""
    p = Path(path)
    if not p.exists():
        raise CliError(f"{option}: {p}: file not found")
    if p.is_dir():
        raise CliError(f"{option}: {p} is a folder, not a file")
    if not p.is_file():
        raise CliError(f"{option}: {p} is not a regular file (a device, pipe or socket)")
    try:
        with p.open("rb") as fh:
            fh.read(1)
    except OSError as exc:
        raise CliError(f"{option}: {p}: cannot read ({exc.strerror or exc})") from None
    return p


def same_file(a: str | Path, b: str | Path) -> bool:
    """True when two paths name the same file (also through symlinks or hard links)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        pass
    try:
        return Path(a).resolve() == Path(b).resolve()
    except (OSError, RuntimeError):  # a loop of symbolic links, a name too long: not the same as a usable path
        return False


@_os_errors_named
def check_output_file(path: str | Path, force: bool, option: str = "--out",
                      inputs: Iterable[str | Path] = ()) -> Path:
    """Check an output file path before any work: not a folder, not an input, a writable folder, and either
    new or ``force``. Creates the parent folder. Returns the path."""
    _check_spelling(path, option)
    if str(path).endswith(("/", os.sep)):
        raise CliError(f"{option}: {path} ends with '/', which names a folder; give a file name")
    p = Path(path)
    for src in inputs:
        if same_file(p, src):
            raise CliError(f"{option}: {p} is also an input ({src}); it would be overwritten by its own output")
    if p.is_dir():
        raise CliError(f"{option}: {p} is a folder; give a file name")
    if _forbidden(p):
        raise CliError(f"{option}: {p}: not a place for output files (a virtual file system)")
    if p.is_symlink() and not p.exists():
        raise CliError(f"{option}: {p} is a dangling symbolic link")
    if p.exists() and not force:
        raise CliError(f"{option}: {p} exists (use --force to overwrite it)")
    _probe_folder(p.parent if str(p.parent) else Path("."), option, leaf=p.name)
    _claim(p, option)
    return p


@_os_errors_named
def check_output_dir(path: str | Path, force: bool, names: Iterable[str], option: str = "--out",
                     inputs: Iterable[str | Path] = ()) -> Path:
    """Check an output folder before any work: not a file, writable, and none of the files the command writes
    (``names``: file names or glob patterns) already there unless ``force``. Creates the folder."""
    _check_spelling(path, option)
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise CliError(f"{option}: {p} is a file; give a folder")
    for src in inputs:
        if same_file(p, src):
            raise CliError(f"{option}: {p} is also an input ({src})")
    _probe_folder(p, option)
    existing = sorted({str(q) for n in names for q in p.glob(n) if q.is_file() or q.is_dir()})
    for src in inputs:
        for q in existing:
            if same_file(q, src):
                raise CliError(f"{option}: {q} is also an input ({src}); it would be overwritten by an output")
    if existing and not force:
        more = f" and {len(existing) - 1} more" if len(existing) > 1 else ""
        raise CliError(f"{option}: {existing[0]}{more} exist(s) (use --force to overwrite)")
    for q in existing:
        if Path(q).is_dir():
            raise CliError(f"{option}: {q} is a folder where an output file goes")
    _claim(p, option)
    return p


def _tmp_sibling(final: Path) -> Path:
    """A unique temporary name beside ``final`` keeping its suffix (writers pick the format by suffix)."""
    fd, name = tempfile.mkstemp(prefix=f".{final.stem}.partial-", suffix=final.suffix, dir=final.parent)
    os.close(fd)
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(name, 0o666 & ~mask)  # mkstemp's 0600 would make outputs private
    return Path(name)


@contextmanager
def atomic_path(final: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``final``; on success it is renamed onto ``final`` (atomic on one file
    system), on any error or interrupt it is removed and ``final`` stays as it was."""
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_sibling(final)
    try:
        yield tmp
        os.replace(tmp, final)
    except StdoutError:
        tmp.unlink(missing_ok=True)
        raise
    except OSError as exc:  # no space left, a file size limit, an I/O error: named, the old content kept
        tmp.unlink(missing_ok=True)
        raise CliError(f"{final}: cannot write ({exc.strerror or exc}); nothing written") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text_atomic(final: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``final`` through a temporary sibling."""
    with atomic_path(final) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(final)


@contextmanager
def staged_dir(out: str | Path) -> Iterator[Path]:
    """Yield a temporary folder inside ``out``; on success every file in it is moved into ``out`` (each by an
    atomic rename), on any error or interrupt the folder is removed and ``out`` keeps its old files."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".partial-", dir=out))
    try:
        yield stage
        for f in sorted(stage.rglob("*")):
            if f.is_file():
                dest = out / f.relative_to(stage)
                dest.parent.mkdir(parents=True, exist_ok=True)
                os.replace(f, dest)
    except StdoutError:
        raise
    except OSError as exc:  # no space left, a file size limit, an I/O error: named
        raise CliError(f"{out}: cannot write ({exc.strerror or exc})") from None
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def check_free_space(folder: str | Path, need_bytes: float, option: str = "--out") -> None:
    """Refuse when the file system holding ``folder`` has less free space than ``need_bytes``."""
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return
    if need_bytes > free:
        raise CliError(f"{option}: the output needs ~{need_bytes / 2**20:.0f} MiB, {folder} has "
                       f"{free / 2**20:.0f} MiB free")
