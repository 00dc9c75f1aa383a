"""The viewer tests reuse the service tests' helpers (frames, detector, servers)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "service"))
