"""Where the checkout and its configs are, for tests that run tools or read conf/."""
from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
CONF = REPO / "conf"
