"""``sim.memory_traffic``: the swarm core's bytes per agent-step and the bandwidth figures of
``fisc-sim bench`` (issue 40)."""

from __future__ import annotations

import numpy as np
import pytest

from fisc_agent.map.lookup import CommandField
from sim.memory_traffic import (FUSED_FLOOR_BYTES, REFERENCE_PASSES, STEP_PASSES, bandwidth_lines, copy_bandwidth_gb_s,
                                last_level_cache_bytes, step_traffic)
from sim.plant.model import PlantParams
from sim.run import load_command_map
from sim.swarm import Swarm, SwarmConfig


def test_the_counted_bytes_follow_the_swarms_own_arrays():
    """The pass table's sizes are the swarm's array item sizes: a change of dtype (float32 state)
    must change the count, so the table is checked against a real swarm."""
    swarm = Swarm(CommandField.from_map(load_command_map(None)), PlantParams(), SwarmConfig(mode="mean"))
    xyz = swarm._pos.itemsize * 3
    assert xyz == swarm._vel.itemsize * 3 == swarm._thr.itemsize * 3 == 24
    assert swarm._ids.itemsize == swarm._cvbuf.itemsize == swarm._cellbuf.itemsize == swarm._out.itemsize == 8
    tr = step_traffic()
    assert tr.reference == sum(r + w for _, r, w in REFERENCE_PASSES) == 337
    assert tr.as_stepped == sum(r + w for _, r, w in STEP_PASSES) == (3 * xyz + 8) + (3 * xyz + 8 + 1) == 161
    assert swarm._fused is not None  # the step these bytes describe is the fused one
    assert tr.floor == FUSED_FLOOR_BYTES == 3 * xyz + 8 + 8 + 3 * xyz + 8 == 168
    assert tr.as_stepped < tr.floor < tr.reference  # mean mode does not read the ids


def test_cache_size_is_read_from_sysfs_and_unknown_is_none(tmp_path):
    for name, size in (("index0", "32K"), ("index2", "1024K"), ("index3", "32M"), ("index4", "junk")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "size").write_text(size + "\n")
    assert last_level_cache_bytes(tmp_path) == 32 * 2**20
    (tmp_path / "index5").mkdir()
    (tmp_path / "index5" / "size").write_text("1G")
    assert last_level_cache_bytes(tmp_path) == 2**30
    assert last_level_cache_bytes(tmp_path / "missing") is None


def test_bandwidth_lines_place_each_size_against_the_bound_and_the_cache():
    tr = step_traffic()
    rate = 5e9 / tr.as_stepped  # moves 5 GB/s: half of a 10 GB/s bound
    lines = bandwidth_lines({10: rate, 20: rate}, {10: 1000, 20: 1001}, 10.0, llc_bytes=1000)
    assert "copy bandwidth 10.0 GB/s" in lines[0] and f"{tr.as_stepped} B per agent-step" in lines[0]
    assert f"{10e9 / tr.as_stepped:.3g} agent-steps/s" in lines[0]
    assert "5.00 GB/s moved = 50% of the bound" in lines[1] and "fits in the last-level cache" in lines[1]
    assert "streams from memory" in lines[2]  # one byte over the cache
    assert "streams from memory" in bandwidth_lines({1: 1.0}, {1: 0}, 1.0, llc_bytes=None)[1]  # cache unknown


def test_copy_bandwidth_is_positive_and_refuses_empty_sizes():
    assert np.isfinite(copy_bandwidth_gb_s(mib=4, repeats=1)) and copy_bandwidth_gb_s(mib=4, repeats=1) > 0
    for mib, repeats in ((0, 1), (1, 0), (-1, 1)):
        with pytest.raises(ValueError, match="must be > 0"):
            copy_bandwidth_gb_s(mib=mib, repeats=repeats)
