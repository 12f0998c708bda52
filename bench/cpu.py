"""One core for a benchmark's process, so every frames/s it prints is per core."""

import os


def pin_one_core() -> str:
    """Pin this process to the last CPU it may use; says where (or why not)."""
    if not hasattr(os, "sched_setaffinity"):
        return "not pinned (no sched_setaffinity on this system)"
    allowed = sorted(os.sched_getaffinity(0))
    core = allowed[-1]
    os.sched_setaffinity(0, {core})
    return f"pinned to CPU {core} of {len(allowed)} allowed"
