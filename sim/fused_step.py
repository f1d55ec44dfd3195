"""The swarm step in one numba call (issue 40 item 3): the glue between :class:`sim.swarm.Swarm`'s buffers
and the fused kernel ``sim.fused_kernel.fused_step``.

``Swarm.step`` flies it when numba is installed and the step has no command filter and no collider (they
act between the command and the plant, and between the plant and the move).  In modes ``mean``, ``slot``
(without look-ahead) and ``kinetic``, with no assignment cached, one call does the whole step: CV lookup,
command (``kinetic``: ``sim.kinetic_jit.kinetic_rows``, the kernel of ``sim.kinetic_step``, called from
inside), removal flags, return policy, plant sub-steps, move and the removed agents' compaction; with an
assignment cached by ``Swarm.assign`` (a sample of the fields), the call starts from it; and
``Swarm.step(m)`` flies m steps in that one call (``sim.run.simulate`` between two events).  Otherwise
(``interpolated``, ``mean`` / ``slot`` with look-ahead) the swarm assigns and fills the commands first,
and one call per step does the return policy, the plant and the move.

The reference is the multi-pass step (``Swarm.step`` with ``fused=False``: the kernels of
``sim.kernels`` and the plant kernel); both give the same bits (tests/sim/test_fused_step.py).
"""

from __future__ import annotations

import numpy as np

from sim.cv_lookup import CVLookup
from sim.kinetic_step import KineticStep
from sim.plant.kernel import kernel_args
from sim.plant.model import PlantCoefficients, substep_count


class FusedStep:
    """The fused step of one swarm's tables (``make`` returns None without numba)."""

    def __init__(self, kernel, lookup: CVLookup, centers_m: np.ndarray, mean_speed: np.ndarray,
                 mean_ned: np.ndarray, slot_ned: np.ndarray, n_star: np.ndarray, slot_mode: bool,
                 co: PlantCoefficients, dt_s: float, x_outlet_m: float, escape_grace_s: float,
                 return_gain_1_s: float, return_speed_fraction: float, map_to_ned: np.ndarray,
                 kinetic: KineticStep | None = None) -> None:
        self._kernel = kernel
        self._kinetic = kinetic
        nsub = substep_count(dt_s, co)
        h = dt_s / nsub
        _, shared = kernel_args(co, h)
        lk = lookup
        self._tables = (lk._origin, lk._inv_l, lk._hi, lk._strides, lk._flat, lk._near, centers_m, mean_speed,
                        mean_ned, slot_ned, n_star, bool(slot_mode), float(x_outlet_m), float(escape_grace_s),
                        float(dt_s), float(return_gain_1_s), float(return_speed_fraction), map_to_ned, shared,
                        float(h), int(nsub), map_to_ned * dt_s)
        # the kinetic mode's tables (but its map_to_ned, the same); other modes: placeholders of their types
        self._kin_tables = kinetic.tables[:-1] if kinetic is not None else \
            (np.zeros(3), 1.0, np.zeros(3), np.zeros(3), 0.0, np.zeros(1, dtype=np.int64), np.zeros((1, 3)),
             np.zeros((1, 3)), np.zeros((1, 3), dtype=np.int64), np.zeros((1, 3)), 0.0, 0.0)

    @classmethod
    def make(cls, *args, **kwargs) -> "FusedStep | None":
        """The fused step (arguments of the constructor but the kernel; ``kinetic``: the swarm's kinetic commands,
        when it flies that mode), or None when numba is not installed."""
        try:
            from sim.fused_kernel import fused_step
        except ModuleNotFoundError as exc:
            if exc.name != "numba":
                raise
            return None
        return cls(fused_step, *args, **kwargs)

    def step(self, swarm, steps: int = 1) -> None:
        """``swarm.step(steps)`` (a :class:`sim.swarm.Swarm` without command filter or collider) through the
        kernel: the counters, the clock and the state as that many multi-pass steps leave them.  Several steps
        are one kernel call where the whole step is the kernel's (modes ``mean``, ``slot`` without look-ahead
        and ``kinetic``), else one call per step."""
        cfg = swarm.config
        kin = self._kinetic
        one_call = kin is not None or (cfg.mode in ("mean", "slot") and cfg.lookahead_s == 0)
        for _ in range(1 if one_call else steps):
            whole = swarm._cv is None and one_call
            cv = swarm._cvbuf[:swarm.n] if whole else swarm.assign()
            n = swarm.n
            if not whole and n and kin is None:
                swarm._select_commands(cv, swarm._cmd[:n], swarm.t_s, into_buffer=True)
            k = steps if one_call else 1
            keep = np.empty(n, dtype=bool)
            n_exit, n_esc, n_out, agent_steps, swarm.n = self._kernel(
                swarm._pos[:n], swarm._vel[:n], swarm._thr[:n], swarm._ids[:n], swarm._out[:n], swarm._cmd[:n], cv,
                keep, not whole, *self._tables, kin is not None, float(swarm.t_s),
                1.0 if kin is None else kin.persistence_s, 0.0 if kin is None else kin.lookahead_s, swarm._epoch[:n],
                swarm._sign[:n], swarm._dir[:n], swarm._phase[:n], *self._kin_tables, k)
            c = swarm.counters
            c.exited += n_exit  # the kernel dropped their rows (Swarm._keep)
            c.escaped += n_esc
            c.steps += k
            c.agent_steps += agent_steps
            c.returned += n_out
            for _ in range(k):
                swarm.t_s += cfg.dt_s
            swarm._cv = None
            swarm._cmd_ready = False
