"""Where the project lives (the repository root and its config folder, read by the config system and the stages),
whether it can write where a config says (:func:`check_folder`), and a file written whole or not at all
(:func:`write_atomic`)."""

import os
import tempfile
from pathlib import Path

from pipeline.errors import ConfigError

REPO_ROOT = Path(__file__).resolve().parents[1]
CONF_DIR = REPO_ROOT / "conf"


def check_folder(value, field: str) -> None:
    """`value` must be a folder this process can write in, or one it can create: tried for real (a uniquely named
    temporary folder made in it, or in its nearest existing parent, then removed), so a read-only or virtual
    filesystem (`/proc/...`), a file in the way or a missing permission is one error naming `field`; nothing is
    left behind, and checks running at once never meet."""
    p = parent = Path(str(value)).expanduser()
    if p.exists() and not p.is_dir():
        raise ConfigError(field, f"{p} is a file, not a folder")
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise ConfigError(field, f"cannot create {p}: {parent} is a file")
    try:
        tempfile.TemporaryDirectory(dir=parent, prefix=".write-check-").cleanup()
    except OSError as err:
        raise ConfigError(field, f"cannot create or write {p}: {err.strerror or err}") from None


def write_atomic(path, text: str) -> Path:
    """`text` into `path`, whole or not at all: written to a uniquely named file beside it, then renamed over it, so
    that a reader (another job of a sweep reading the same index) never sees it empty or half written."""
    path = Path(path)
    with tempfile.NamedTemporaryFile("w", dir=path.parent, prefix=f".{path.name}.", suffix=".tmp", delete=False) as f:
        tmp = Path(f.name)
        try:
            f.write(text)
        except BaseException:  # nothing half written is left beside it, and `path` keeps what it had
            f.close()
            tmp.unlink()
            raise
    os.chmod(tmp, 0o644)  # a plain file's mode (not the temporary file's 0600)
    tmp.replace(path)
    return path
