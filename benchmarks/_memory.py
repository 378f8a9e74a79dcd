"""Peak-memory helpers shared by the benchmark scripts (Linux /proc; resource as a fallback)."""

from __future__ import annotations

import resource


def reset_peak() -> None:
    """Reset the kernel's peak-RSS counter (Linux: writing 5 to clear_refs), so the peak is this case's."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
    except OSError:
        pass


def status_mb(key: str) -> float:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def rss_mb() -> float:
    return status_mb("VmRSS")


def peak_mb() -> float:
    return status_mb("VmHWM")
