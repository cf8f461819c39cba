"""Tracked, content-addressed stage outputs (datasets, models, error maps).

A tracked output lives in ``<root>/<name>-<id>/`` where ``id`` is a short hash of everything that
determines its bytes (the resolved recipe minus volatile keys, the input ids, the code version).
Inside, ``manifest.json`` records the id, the recipe, the inputs, the package version and git commit,
the creation time and the sha256 and size of every file.

Writes are atomic: :func:`tracked_output` yields a temporary folder next to the final one and renames it
only when the body finished without an exception, after writing the manifest. A folder without a valid
manifest is never taken for a finished output.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import re
import shutil
import subprocess
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from pipeline import __version__
from pipeline.errors import DatasetError, PipelineError

MANIFEST = "manifest.json"
ID_LEN = 10
_TMP_PREFIX = ".tmp-"
# a tracked folder of at most this many bytes is re-hashed before use (`verify(full=None)`): maps, error maps and
# results in milliseconds; a bigger dataset gets its sizes checked (`make verify-data` re-hashes it)
HASH_LIMIT = 64 * 2**20
_HASHED: dict[Path, tuple] = {}  # folders re-hashed in this process -> their files' sizes and times then


# ----------------------------------------------------------------------------------------- hashing
def canonical_json(obj: Any) -> str:
    """Deterministic JSON (sorted keys, no whitespace) of plain containers."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


def content_id(*parts: Any) -> str:
    """Short sha256 of the canonical JSON of `parts`."""
    return hashlib.sha256(canonical_json(list(parts)).encode()).hexdigest()[:ID_LEN]


def sha256_file(path: Path, chunk: int = 1 << 22) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def strip_keys(recipe: Mapping, volatile: tuple[str, ...]) -> dict:
    """Copy of a nested mapping without the `volatile` keys (at any depth)."""
    out = {}
    for k, v in recipe.items():
        if k in volatile:
            continue
        out[k] = strip_keys(v, volatile) if isinstance(v, Mapping) else v
    return out


def code_version(*packages: str) -> str:
    """Hash of the source files of the given sub-packages/modules of `pipeline` (e.g. "render").

    Changing the rendering code changes dataset ids; changing unrelated code does not.
    """
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for pkg in sorted(packages):
        target = root / pkg
        if target.is_dir():
            files = sorted(target.rglob("*.py"))
        elif target.with_suffix(".py").is_file():
            files = [target.with_suffix(".py")]
        else:
            raise ValueError(f"code_version: no module pipeline/{pkg}")
        for f in files:
            h.update(str(f.relative_to(root)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:ID_LEN]


def git_commit() -> str | None:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parents[1],
            capture_output=True, text=True, timeout=5, check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def package_version() -> str:
    try:
        from importlib.metadata import version

        return version("hycontrol-vision")
    except Exception:  # noqa: BLE001 - not installed (running from a source tree)
        return __version__


# ---------------------------------------------------------------------------------------- manifest
def file_table(folder: Path) -> dict[str, dict]:
    files = {}
    for f in sorted(folder.rglob("*")):
        if f.is_file() and f.name != MANIFEST:
            files[f.relative_to(folder).as_posix()] = {"sha256": sha256_file(f), "size": f.stat().st_size}
    return files


def write_manifest(folder: Path, meta: Mapping) -> dict:
    manifest = {
        **meta,
        "package_version": package_version(),
        "git_commit": git_commit(),
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "files": file_table(folder),
    }
    (folder / MANIFEST).write_text(json.dumps(manifest, indent=2, sort_keys=True, default=str) + "\n")
    return manifest


def read_manifest(folder: Path) -> dict:
    path = Path(folder) / MANIFEST
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"{folder}: no {MANIFEST} (incomplete or not a tracked output)") from None
    except NotADirectoryError:
        raise DatasetError(f"{folder}: a file where a tracked output's folder should be; move it away") from None
    except json.JSONDecodeError as err:
        raise DatasetError(f"{path}: unreadable manifest ({err.msg})") from None


def verify(folder: Path, *, full: bool | None = True) -> list[str]:
    """Problems of a tracked folder, one line each naming the file (empty list: all good).

    `full=False` checks presence and sizes only; `None` also re-hashes a folder of at most `HASH_LIMIT` bytes (a
    map, an error map, an experiment's results, a small dataset: cheap), once per process while its files keep
    their sizes and times.
    """
    folder = Path(folder)
    try:
        manifest = read_manifest(folder)
    except DatasetError as err:
        return [str(err)]
    files = manifest.get("files", {})
    if full is None:
        full = sum(int(info.get("size", 0)) for info in files.values()) <= HASH_LIMIT
    stamp = _stamp(folder, files) if full else None
    if stamp is not None and _HASHED.get(folder.resolve()) == stamp:
        full = False  # re-hashed in this process already, nothing touched since
    problems = []
    for rel, info in sorted(files.items()):
        path = folder / rel
        if not path.is_file():
            problems.append(f"{path}: missing")
            continue
        size = path.stat().st_size
        if size != info["size"]:
            problems.append(f"{path}: size {size} != {info['size']} in manifest (truncated or altered)")
        elif full and sha256_file(path) != info["sha256"]:
            problems.append(f"{path}: sha256 mismatch (altered)")
    expected = folder.name.rsplit("-", 1)[-1]
    if manifest.get("id") != expected:
        problems.append(f"{folder}: manifest id {manifest.get('id')!r} != folder id {expected!r}")
    if full and not problems and stamp is not None:
        _HASHED[folder.resolve()] = stamp
    return problems


def _stamp(folder: Path, files: Mapping) -> tuple | None:
    """Sizes and modification times of a folder's files (None: one is missing)."""
    try:
        return tuple((rel, (st := (folder / rel).stat()).st_size, st.st_mtime_ns) for rel in sorted(files))
    except OSError:
        return None


def exists(folder: Path, kind: str = "tracked output") -> bool:
    """Whether a tracked output's folder exists; a file (or anything else) in its place is a DatasetError."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise DatasetError(f"{folder}: a file where the {kind}'s folder should be; move it away (nothing here "
                           "reads or replaces it)")
    return folder.is_dir()


def check_intact(folder: Path, kind: str = "tracked output", rebuild: str | None = None,
                 full: bool | None = None) -> Path:
    """`folder` when it matches its manifest (sizes always; sha256 as :func:`verify` with `full`), else a one-line
    DatasetError naming the first damaged file and the command that rebuilds it (`rebuild`)."""
    folder = Path(folder)
    if not exists(folder, kind):
        raise DatasetError(f"{kind} {folder} does not exist" + (f"; run `{rebuild}`" if rebuild else ""))
    problems = verify(folder, full=full)
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        fix = f"rebuild it with `{rebuild}`" if rebuild else "rebuild it with the command that made it and force=true"
        raise DatasetError(f"damaged {kind} {folder.name}: {problems[0]}{more}; {fix}")
    return folder


def is_complete(folder: Path, kind: str = "tracked output") -> bool:
    """A finished output of that name is there (sizes checked; a file in its place is a DatasetError)."""
    return exists(folder, kind) and not verify(folder, full=False)


# -------------------------------------------------------------------------------------- resolution
def entries(root: Path, name: str | None = None) -> list[Path]:
    """Finished tracked folders under `root` (optionally of one name), newest first."""
    root = Path(root)
    if not root.is_dir():
        return []
    out = []
    for d in root.iterdir():
        if not d.is_dir() or d.name.startswith(_TMP_PREFIX) or not (d / MANIFEST).is_file():
            continue
        if name is not None and d.name.rsplit("-", 1)[0] != name:
            continue
        out.append(d)

    def created(d: Path) -> str:
        try:
            return read_manifest(d).get("created", "")
        except PipelineError:
            return ""

    return sorted(out, key=lambda d: (created(d), d.stat().st_mtime), reverse=True)


def resolve(root: Path, ref: str | os.PathLike, *, kind: str = "output", expected=None, command=None,
            field: str | None = None, check: bool = True) -> Path:
    """:func:`find`, then (`check`) :func:`check_intact`: a damaged output is one line naming the file and the
    command that rebuilds it (`command` of its name, with `force=true`)."""
    folder = find(root, ref, kind=kind, expected=expected, command=command, field=field)
    if check:
        cmd = _command_fn(command)
        rebuild = cmd(folder.name.rsplit("-", 1)[0]) if cmd is not None else None
        check_intact(folder, kind, f"{rebuild} force=true" if rebuild else None)
    return folder


def find(root: Path, ref: str | os.PathLike, *, kind: str = "output", expected=None, command=None,
         field: str | None = None) -> Path:
    """A tracked folder from a path, `name-id`, an id, or a name (see :mod:`pipeline.lineage`).

    A bare name never means "the newest folder": `expected(name) -> id | None` gives the id the upstream
    stage's current config produces, and `<name>-<id>` is returned when it is built. A name that no config
    produces resolves only when exactly one folder has it; several candidates are an error listing them.
    `command` (a string with `{name}`, or `name -> command line`) and `field` make the error messages say how
    to build or pin one.
    """
    cmd = _command_fn(command)
    ref_s = str(ref)
    p = Path(ref_s)
    if p.is_dir() and (p / MANIFEST).is_file():
        return p
    for place in ([p] if os.sep in ref_s else []) + [Path(root) / ref_s]:
        exists(place, kind)  # a file where a folder should be: one line
    all_entries = entries(root)
    for d in all_entries:  # exact folder name or id
        if d.name == ref_s or d.name.rsplit("-", 1)[-1] == ref_s:
            return d
    named = sorted((d for d in all_entries if d.name.rsplit("-", 1)[0] == ref_s), key=lambda d: d.name)
    pin = f" (pin one with {field}=<name-id>)" if field else " (pin one by its id or name-id)"
    others = f"; other builds: {', '.join(d.name for d in named)}{pin}" if named else ""
    base = re.fullmatch(rf"(.+)-[0-9a-f]{{{ID_LEN}}}", ref_s)
    if base and expected is not None:  # a pinned `name-id` that is not built: say so, and what makes `name`
        made = cmd is not None and expected(base.group(1)) is not None  # no command for a name no config makes
        make = f"; `{cmd(base.group(1))}` makes the current config's" if made else ""
        raise DatasetError(f"{kind} {ref_s} is not built under {root}{make}")
    make = f"; run `{cmd(ref_s)}`" if cmd else ""
    want = expected(ref_s) if expected is not None else None
    if want is not None:
        folder = Path(root) / f"{ref_s}-{want}"
        if exists(folder, kind) and folder in all_entries:
            return folder
        raise DatasetError(f"{kind} {ref_s!r}: the current config makes {ref_s}-{want}, which is not built under "
                           f"{root}{make}{others}")
    if len(named) == 1:
        return named[0]
    if len(named) > 1:
        raise DatasetError(f"{kind} {ref_s!r} is ambiguous: {', '.join(d.name for d in named)}{pin}")
    known = sorted({d.name.rsplit("-", 1)[0] for d in all_entries})
    hint = f"known: {', '.join(known)}" if known else f"none under {root}"
    raise DatasetError(f"unknown {kind} {ref_s!r} ({hint}){make if expected is None else ''}")  # no config makes it


def _command_fn(command):
    """`name -> command line` from a template with `{name}`, a function, or None."""
    if command is None or callable(command):
        return command

    def fmt(name: str) -> str:
        return command.format(name=name)

    return fmt


def stale_temporaries(root: Path, remove: bool = True, echo=print) -> list[Path]:
    """Temporary folders under `root` left by processes that no longer run (a `kill -9`): removed, or
    only reported with their size when `remove` is false."""
    root = Path(root)
    if not root.is_dir():
        return []
    found = []
    for d in root.iterdir():
        if not (d.is_dir() and d.name.startswith(_TMP_PREFIX)):
            continue
        try:
            pid = int(d.name.rsplit("-", 1)[-1])
        except ValueError:
            continue
        if pid == os.getpid() or _alive(pid):
            continue
        size = sum(f.stat().st_size for f in d.rglob("*") if f.is_file())
        found.append(d)
        if remove:
            shutil.rmtree(d, ignore_errors=True)
        echo(f"{'removed' if remove else 'found'} stale temporary folder {d} ({size / 2**20:.1f} MiB) of "
             f"process {pid}, which no longer runs")
    return found


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


# ----------------------------------------------------------------------------------------- writing
@contextlib.contextmanager
def tracked_output(root: Path, name: str, id_: str, meta: Mapping) -> Iterator[Path]:
    """Yield a temporary folder; on success write the manifest and rename it to `<root>/<name>-<id>`.

    On any exception (including KeyboardInterrupt) the temporary folder is removed and nothing appears
    under the final name. An existing final folder is replaced only after the new one is complete.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    stale_temporaries(root)
    final = root / f"{name}-{id_}"
    exists(final)  # a file in the way is the user's to move, not ours to replace
    tmp = root / f"{_TMP_PREFIX}{name}-{id_}-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        yield tmp
        write_manifest(tmp, {"id": id_, "name": name, **meta})
        if final.exists():
            old = root / f"{_TMP_PREFIX}old-{name}-{id_}-{os.getpid()}"
            final.rename(old)
            tmp.rename(final)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def to_plain(obj: Any) -> Any:
    """OmegaConf containers -> plain Python (for hashing and manifests)."""
    if isinstance(obj, DictConfig | ListConfig):
        return OmegaConf.to_container(obj, resolve=True)
    return obj


def to_plain_lenient(node: Any) -> Any:
    """Plain Python of a config node; a value whose interpolation cannot resolve here (`${hydra:...}` outside a
    Hydra app) is kept as its `${...}` text."""
    if isinstance(node, DictConfig):
        out = {}
        for key in node:
            try:
                out[key] = to_plain_lenient(OmegaConf.select(node, str(key), throw_on_resolution_failure=True))
            except Exception:  # noqa: BLE001 - InterpolationResolutionError and friends
                out[key] = OmegaConf.to_container(node, resolve=False)[key]
        return out
    if isinstance(node, ListConfig):
        return [to_plain_lenient(v) for v in node]
    return node
