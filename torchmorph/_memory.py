"""How much memory a device can still give: the one rule the dense-or-matrix-free choices
of IDW and RBF share."""

from __future__ import annotations

import os

import torch

__all__ = ["free_memory"]


def free_memory(device: torch.device) -> int:
    """Bytes the device can still allocate: CUDA's free memory plus what torch's caching
    allocator holds unused; on the CPU the kernel's MemAvailable (physical memory if
    unknown)."""
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        stats = torch.cuda.memory_stats(device)
        return int(
            free
            + stats.get("reserved_bytes.all.current", 0)
            - stats.get("allocated_bytes.all.current", 0)
        )
    try:
        with open("/proc/meminfo") as info:
            for line in info:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return 2**63 - 1
