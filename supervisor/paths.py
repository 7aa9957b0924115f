"""Where the embedded configuration lives."""

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
CONFIG_DIR = REPO_ROOT / "config"
SCENES_DIR = CONFIG_DIR / "scenes"
DEFAULT_CONFIG = CONFIG_DIR / "default.yaml"
