"""Host helpers shared by the kernel pipelines: memory checks, prefix sums, compaction."""

from __future__ import annotations

import os

import warp as wp

from ._errors import ResourceError
from ._parallel import launch

__all__ = ["available_memory", "check_memory", "scan", "compact"]


def available_memory(device) -> int:
    """Bytes that can still be allocated on ``device`` (host RAM for the CPU)."""
    device = wp.get_device(device)
    if device.is_cuda:
        return int(device.free_memory)
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES"))


def check_memory(who: str, stage: str, need: int, limit: int) -> None:
    """Raise :class:`ResourceError` with the estimate when ``need`` bytes exceed ``limit``."""
    if need > limit:
        raise ResourceError(
            f"{who}: the {stage} stage needs an estimated {need / 2**20:.1f} MiB, "
            f"more than the {limit / 2**20:.1f} MiB available; use a larger cellsize or smaller bounds"
        )


def scan(counts: wp.array) -> tuple[wp.array, int]:
    """Exclusive prefix sum of int32 ``counts`` and the total (one host sync)."""
    offsets = wp.empty_like(counts)
    if counts.shape[0] == 0:
        return offsets, 0
    wp.utils.array_scan(counts, offsets, inclusive=False)
    # host sync: the total sizes the next stage's allocation
    return offsets, int(offsets[-1:].numpy()[0]) + int(counts[-1:].numpy()[0])


@wp.kernel(enable_backward=False)
def compact_kernel(
    flags: wp.array(dtype=wp.int32), scanned: wp.array(dtype=wp.int32), offset: int, out: wp.array(dtype=wp.int32)
):
    """``out[scanned[i]] = i`` for every flagged ``i`` (exclusive scan)."""
    tid = wp.tid() + offset
    if flags[tid] != 0:
        out[scanned[tid]] = tid


def compact(flags: wp.array, device, threads=None) -> wp.array:
    """Indices of the non-zero entries of int32 ``flags``, ascending."""
    offsets, total = scan(flags)
    out = wp.empty(total, dtype=wp.int32, device=device)
    launch(compact_kernel, flags.shape[0], [flags, offsets], [out], device, threads)
    return out
