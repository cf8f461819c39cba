"""Where the project lives: the repository root and its config folder (read by the config system and the stages)."""

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
CONF_DIR = REPO_ROOT / "conf"
