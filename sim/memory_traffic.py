"""The swarm core against the machine's memory bandwidth (``fisc-sim bench``, issue 40).

Two figures put an agent-steps/s rate in context:

- the **bytes moved per agent-step**: for each pass of ``Swarm.step`` (mean mode, numba
  kernels: since 2026-12-05 one fused pass, ``sim.fused_kernel``), the bytes of every per-agent array
  it reads and writes, summed over the passes (each pass streams its arrays once), beside the same
  count for the multi-pass reference step (``SwarmConfig(fused=False)``) and the **floor**: one pass
  that reads and writes the agent state once (position, velocity, thrust state, time outside) and
  reads its id;
- the **measured memory bandwidth**: a STREAM-style copy ``c = a`` over arrays far larger than the
  last-level cache, best of a few repeats, counted as STREAM counts it (one read and one write per
  element).

The bound is bandwidth / bytes: the rate the step would reach if memory were its only cost.  A
swarm whose state fits in the last-level cache is bounded by the cache, not by this figure.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

F8, I8, B1 = 8, 8, 1  # bytes of a float64, an int64 and a bool
XYZ = 3 * F8

STEP_PASSES: tuple[tuple[str, int, int], ...] = (
    # pass, bytes read per agent, bytes written per agent
    ("fused step: position, velocity, thrust, time outside -> the same, keep flag", 3 * XYZ + F8, 3 * XYZ + F8 + B1),
)
"""``Swarm.step``'s passes over per-agent arrays, mean mode with the numba kernels: the one pass of
``sim.fused_kernel.fused_step`` (the CV, the command and the plant's inner state stay in a block of
256 agents in L1; the lookup tables and an outside agent's return inputs are not counted)."""

REFERENCE_PASSES: tuple[tuple[str, int, int], ...] = (
    # pass (sim.kernels), bytes read per agent, bytes written per agent
    ("lookup: position, id -> CV, command, cell", XYZ + I8, I8 + XYZ + I8),
    ("removal: position, CV, cell, time outside -> keep", XYZ + I8 + I8 + F8, B1),
    ("returns: CV, time outside -> time outside", I8 + F8, F8),
    ("plant: velocity, thrust, command -> velocity, thrust", 3 * XYZ, 2 * XYZ),
    ("move: position, velocity -> position", 2 * XYZ, XYZ),
)
"""The multi-pass reference step's passes (``SwarmConfig(fused=False)``, mean mode, numba kernels; an
agent outside the CVs also reads its return command's inputs: rare, not counted)."""

FUSED_FLOOR_BYTES = (3 * XYZ + F8 + I8) + (3 * XYZ + F8)
"""One fused pass: read position, velocity, thrust state, time outside and id; write all but the id."""


@dataclass(frozen=True)
class Traffic:
    """Bytes per agent-step of the swarm core."""

    as_stepped: int
    """Summed over ``STEP_PASSES`` (each pass streams its arrays once) [B]."""
    reference: int
    """Summed over ``REFERENCE_PASSES``, the multi-pass reference step [B]."""
    floor: int
    """One fused pass over the agent state (``FUSED_FLOOR_BYTES``) [B]."""


def step_traffic() -> Traffic:
    """Bytes moved per agent-step by ``Swarm.step`` as it is, by its multi-pass reference, and the floor."""
    return Traffic(sum(r + w for _, r, w in STEP_PASSES), sum(r + w for _, r, w in REFERENCE_PASSES),
                   FUSED_FLOOR_BYTES)


def copy_bandwidth_gb_s(mib: int = 512, repeats: int = 5) -> float:
    """Memory bandwidth [GB/s] of ``c = a`` on two float64 arrays of ``mib`` MiB each, the best of
    ``repeats`` (STREAM's count: 2 x the array bytes per copy)."""
    if mib <= 0 or repeats <= 0:
        raise ValueError(f"mib and repeats must be > 0, got {mib}, {repeats}")
    n = mib * 2**20 // F8
    a, c = np.ones(n), np.zeros(n)  # filled: every page is touched before timing
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        np.copyto(c, a)
        best = min(best, time.perf_counter() - t0)
    return 2 * n * F8 / best / 1e9


def last_level_cache_bytes(cpu: Path = Path("/sys/devices/system/cpu/cpu0/cache")) -> int | None:
    """Size of the largest CPU cache (Linux sysfs), None when unknown."""
    sizes = []
    for level in cpu.glob("index*"):
        try:
            text = (level / "size").read_text().strip()
        except OSError:
            continue
        unit = {"K": 2**10, "M": 2**20, "G": 2**30}.get(text[-1:].upper(), 1)
        digits = text[:-1] if text[-1:].isalpha() else text
        if digits.isdigit():
            sizes.append(int(digits) * unit)
    return max(sizes) if sizes else None


def bandwidth_lines(rates: dict[int, float], state_bytes: dict[int, int], bandwidth_gb_s: float,
                    llc_bytes: int | None) -> list[str]:
    """The bench's lines: bytes per agent-step, the bound, and each size's fraction of it."""
    tr = step_traffic()
    bound = bandwidth_gb_s * 1e9 / tr.as_stepped
    floor_bound = bandwidth_gb_s * 1e9 / tr.floor
    lines = [f"memory: copy bandwidth {bandwidth_gb_s:.1f} GB/s (one core); the step moves {tr.as_stepped} B per "
             f"agent-step in {len(STEP_PASSES)} pass(es) (the multi-pass reference {tr.reference} B; floor "
             f"{tr.floor} B): memory-bound rate {bound:.3g} agent-steps/s ({floor_bound:.3g} at the floor)"]
    for n, rate in rates.items():
        where = ("fits in the last-level cache: the cache, not memory, bounds it"
                 if llc_bytes is not None and state_bytes[n] <= llc_bytes else "streams from memory")
        lines.append(f"memory: {n:>8d} agents: {rate * tr.as_stepped / 1e9:.2f} GB/s moved = "
                     f"{rate / bound:.0%} of the bound ({where})")
    return lines
