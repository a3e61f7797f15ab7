"""Shared test setup: headless pygame and the src layout on the import path."""

from __future__ import annotations

import os
import sys
from pathlib import Path

# Rendering tests (and any pygame import) must not need a display.
os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

_SRC = Path(__file__).resolve().parents[1] / "src"
if _SRC.is_dir() and str(_SRC) not in sys.path:
    sys.path.insert(0, str(_SRC))
