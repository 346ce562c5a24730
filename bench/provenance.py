"""Which code a benchmark row was measured with (every bench/results JSON records it)."""
import os
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent


def code_commit(watched=("python/matlearn",)) -> str:
    """MATLEARN_SUITE_COMMIT (set when running a snapshot of a commit), else HEAD of this
    checkout, "+dirty" when any of the `watched` paths (relative to the repository root) has
    uncommitted edits; "unknown" without git."""
    if os.environ.get("MATLEARN_SUITE_COMMIT"):
        return os.environ["MATLEARN_SUITE_COMMIT"]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", *watched], cwd=ROOT.parent,
                               capture_output=True, text=True).stdout.strip()
        return head + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
