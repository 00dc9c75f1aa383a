"""The chaos suite reuses the service tests' helpers (frames, detector, servers) and the store tests' objects and
snapshot files: tests/service and tests/stores on sys.path."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "service"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "stores"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
