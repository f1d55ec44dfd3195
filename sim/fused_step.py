"""The swarm step in one numba call (issue 40 item 3): the glue between :class:`sim.swarm.Swarm`'s buffers
and the fused kernel ``sim.fused_kernel.fused_step``.

``Swarm.step`` flies it when numba is installed and the step has no command filter and no collider (they
act between the command and the plant, and between the plant and the move).  In modes ``mean`` and
``slot`` without look-ahead, with no assignment cached, one call does the whole step: CV lookup, command,
removal flags, return policy, plant sub-steps and move.  Otherwise (``kinetic``, ``interpolated``,
look-ahead, or an assignment cached by ``Swarm.assign``) the swarm assigns and fills the commands first,
and one call does the return policy, the plant and the move.

The reference is the multi-pass step (``Swarm.step`` with ``fused=False``: the kernels of
``sim.kernels`` and the plant kernel); both give the same bits (tests/sim/test_fused_step.py).
"""

from __future__ import annotations

import numpy as np

from sim.cv_lookup import CVLookup
from sim.plant.kernel import kernel_args
from sim.plant.model import PlantCoefficients, substep_count


class FusedStep:
    """The fused step of one swarm's tables (``make`` returns None without numba)."""

    def __init__(self, kernel, lookup: CVLookup, centers_m: np.ndarray, mean_speed: np.ndarray,
                 mean_ned: np.ndarray, slot_ned: np.ndarray, n_star: np.ndarray, slot_mode: bool,
                 co: PlantCoefficients, dt_s: float, x_outlet_m: float, escape_grace_s: float,
                 return_gain_1_s: float, return_speed_fraction: float, map_to_ned: np.ndarray) -> None:
        self._kernel = kernel
        nsub = substep_count(dt_s, co)
        h = dt_s / nsub
        _, shared = kernel_args(co, h)
        lk = lookup
        self._tables = (lk._origin, lk._inv_l, lk._hi, lk._strides, lk._flat, lk._near, centers_m, mean_speed,
                        mean_ned, slot_ned, n_star, bool(slot_mode), float(x_outlet_m), float(escape_grace_s),
                        float(dt_s), float(return_gain_1_s), float(return_speed_fraction), map_to_ned, shared,
                        float(h), int(nsub), map_to_ned * dt_s)

    @classmethod
    def make(cls, *args, **kwargs) -> "FusedStep | None":
        """The fused step (arguments of the constructor but the kernel), or None when numba is not installed."""
        try:
            from sim.fused_kernel import fused_step
        except ModuleNotFoundError as exc:
            if exc.name != "numba":
                raise
            return None
        return cls(fused_step, *args, **kwargs)

    def step(self, swarm) -> None:
        """``swarm.step()`` (a :class:`sim.swarm.Swarm` without command filter or collider) through the kernel:
        the counters, the clock and the state as its multi-pass step leaves them."""
        cfg = swarm.config
        whole = swarm._cv is None and cfg.mode in ("mean", "slot") and cfg.lookahead_s == 0
        cv = swarm._cvbuf[:swarm.n] if whole else swarm.assign()
        n = swarm.n
        if not whole and n:
            swarm._select_commands(cv, swarm._cmd[:n], swarm.t_s, into_buffer=True)
        keep = np.empty(n, dtype=bool)
        n_exit, n_esc, n_out = self(swarm.pos_m, swarm.vel_ned_m_s, swarm.thrust_ned_m_s2, swarm.ids,
                                    swarm.outside_s, swarm._cmd[:n], cv, keep, not whole)
        c = swarm.counters
        if n_exit or n_esc:
            c.exited += n_exit
            c.escaped += n_esc
            swarm._keep(keep, cv)
        c.steps += 1
        c.agent_steps += swarm.n
        c.returned += n_out
        swarm.t_s += cfg.dt_s
        swarm._cv = None
        swarm._cmd_ready = False

    def __call__(self, pos: np.ndarray, vel: np.ndarray, thr: np.ndarray, ids: np.ndarray, out_s: np.ndarray,
                 cmd: np.ndarray, cv: np.ndarray, keep: np.ndarray, assigned: bool) -> tuple[int, int, int]:
        """Step the (n, 3) rows ``pos``, ``vel``, ``thr`` (and ``out_s``, ``cmd``) in place; returns
        ``(n_exited, n_escaped, n_outside)``.  ``assigned``: ``cv`` and ``cmd`` hold the agents' CVs and
        commands (removals done; read only); else the kernel looks them up itself (``cv`` and ``cmd`` are
        left as they were) and ``keep`` flags the agents that stay."""
        return self._kernel(pos, vel, thr, ids, out_s, cmd, cv, keep, assigned, *self._tables)
