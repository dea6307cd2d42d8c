"""What every benchmark report states about the machine it ran on."""

import os
import platform
from pathlib import Path

import numpy as np


def machine() -> str:
    """CPU model and count, OS, Python and numpy versions, and the load when the run started."""
    cpu = platform.processor() or "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    return (f"{cpu} ({os.cpu_count()} cores), {platform.system()} {platform.release()}, Python "
            f"{platform.python_version()}, numpy {np.__version__}; load average at start {load} "
            "(a shared machine: timings vary by up to 2x between runs)")
