"""Fault injection logic: seeded loss, delay line, position dropout windows."""

from __future__ import annotations

import pytest

from sim.autopilot.faults import DelayLine, FaultConfig, FaultInjector, parse_dropout


def test_loss_is_seeded_and_close_to_the_probability():
    a = FaultInjector(FaultConfig(loss_probability=0.3, seed=42))
    b = FaultInjector(FaultConfig(loss_probability=0.3, seed=42))
    da = [a.drop_outgoing() for _ in range(2000)]
    assert da == [b.drop_outgoing() for _ in range(2000)]
    assert 0.25 < sum(da) / len(da) < 0.35
    assert a.dropped_out == sum(da)


def test_no_loss_by_default():
    f = FaultInjector()
    assert not any(f.drop_incoming() or f.drop_outgoing() for _ in range(1000))
    assert f.latency_s == 0.0


def test_delay_line_releases_in_due_order():
    d: DelayLine[str] = DelayLine()
    d.push(2.0, "late")
    d.push(1.0, "a")
    d.push(1.0, "b")
    assert d.next_due() == 1.0
    assert d.pop_due(0.5) == []
    assert d.pop_due(1.0) == ["a", "b"]
    assert d.pop_due(5.0) == ["late"] and len(d) == 0


def test_position_dropout_windows():
    f = FaultInjector(FaultConfig(position_dropouts=((1.0, 2.0), (10.0, 0.5))))
    assert [f.position_dropout(t) for t in (0.9, 1.0, 2.9, 3.0, 10.2, 10.6)] == [False, True, True, False, True, False]
    assert parse_dropout("5,2.5") == (5.0, 2.5)
    with pytest.raises(ValueError, match="START,DURATION"):
        parse_dropout("5")
    with pytest.raises(ValueError, match="DURATION >= 0"):
        parse_dropout("5,-1")


def test_invalid_fault_config():
    with pytest.raises(ValueError, match="loss_probability"):
        FaultConfig(loss_probability=1.5)
    with pytest.raises(ValueError, match="latency_s"):
        FaultConfig(latency_s=-0.1)
