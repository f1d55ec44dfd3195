"""``fisc-sim run --safety-net``: the agents' separation safety net (``fisc_agent.flight.safety_net``) flown
by the whole simulated swarm, each step, between the command and the plant.

Every agent hears every other at once with no delay (the simulator's view: reports of age 0, so the
keep-out radius is d_min for every neighbour), and its command becomes ``keep_apart_pairs`` of the
command the flow law gave it.  ``SwarmSafetyNet.apply`` is the ``command_filter`` hook of
``sim.swarm.Swarm``: it adjusts the step's NED commands in place before the plant step.

Frames.  The net needs positions, velocities and commands in one frame: the swarm keeps positions in
the map frame and velocities and commands in NED, so both are turned to the map frame
(``MAP_TO_NED`` is its own inverse) and the result back.

Candidate pairs. The pairs handed to ``keep_apart_pairs`` are those of ``cKDTree(pos).query_pairs(r)`` with
``r = d_min + T * (max_i |cmd_i| + max_j |vel_j|)`` (times 1 + 1e-9 for rounding; ``T`` the horizon,
``effective_horizon_s`` for the plant's lag ``tau_v_s``), recomputed every step from the commands and
velocities of that step. This is exact, not an approximation: a pair acts on agent i only inside d_min or when
i's commanded speed towards the neighbour, at most ``|cmd_i|``, exceeds ``(d - d_min) / T`` less the
neighbour's speed towards i, at most ``|vel_j|``. (Before 2026-12-07 the neighbour's speed towards i did not
count, and the radius was ``d_min + T max_i |cmd_i|``.) With the 1.5 s horizon that was 3.9 m on the default
map (d_min 0.92 m, 2 m/s): ~1.5 x 10^5 pairs among 850 agents spread over the tunnel (the main job's density
without the net; with it the net empties the tunnel, docs/deployment.md).

The duct (``DuctAxis``) is the CVs' length along x about the map's x axis: the net's correction never
points away from it there (the wall rule of ``fisc_agent.flight.safety_net``).

The pairs are evaluated by ``sim.jit_safety_net`` (numba, the same arithmetic as ``keep_apart_pairs``,
tested equal) when numba is installed, else by ``keep_apart_pairs`` itself.

Counts (``SafetyNetCounts``): an agent-step counts as *acted on* when the net changed that agent's
command (two corrections that cancel exactly leave it unchanged and do not count).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fisc_agent.flight.safety_net import (COINCIDENT_M, LIMIT_TOL_M_S, DuctAxis, SafetyNetConfig, effective_horizon_s,
                                          keep_apart_pairs)

#: Map frame <-> NED of the default deployment (``sim.swarm.MAP_TO_NED``; its own inverse).
_MAP_TO_NED = np.array([1.0, 1.0, -1.0])
#: Relative margin on the candidate-pair radius against rounding of the distances.
_REACH_MARGIN = 1e-9


def pairs_kernel():
    """The numba twin of ``keep_apart_pairs`` (``sim.jit_safety_net.keep_apart_pairs``), or None when
    numba is not installed."""
    try:
        from sim import jit_safety_net
    except ModuleNotFoundError as exc:
        if exc.name != "numba":
            raise
        return None
    return jit_safety_net.keep_apart_pairs


def _top_speed_m_s(v_m_s: np.ndarray) -> float:
    """The largest row norm of ``v_m_s`` (n, 3); 0 for none."""
    v = np.asarray(v_m_s, dtype=float).reshape(-1, 3)
    return float(np.sqrt(np.max(np.einsum("ij,ij->i", v, v)))) if v.shape[0] else 0.0


def candidate_reach_m(d_min_m: float, command_m_s: np.ndarray, horizon_s: float,
                      velocity_m_s: np.ndarray | None = None) -> float:
    """The radius within which a pair can act this step [m]: ``d_min + horizon_s (max_i |cmd_i| +
    max_j |vel_j|)`` (module docstring), d_min with no agents."""
    vel = _top_speed_m_s(velocity_m_s) if velocity_m_s is not None else 0.0
    return float(d_min_m + horizon_s * (_top_speed_m_s(command_m_s) + vel))


def candidate_pairs(pos_m: np.ndarray, reach_m: float) -> np.ndarray:
    """(m, 2) int64 index pairs (i < j) of the positions ``pos_m`` (n, 3) at most ``reach_m`` apart
    (``scipy.spatial.cKDTree.query_pairs``)."""
    from scipy.spatial import cKDTree

    pos = np.asarray(pos_m, dtype=float).reshape(-1, 3)
    if pos.shape[0] < 2:
        return np.zeros((0, 2), dtype=np.int64)
    return np.asarray(cKDTree(pos).query_pairs(reach_m, output_type="ndarray"), dtype=np.int64).reshape(-1, 2)


@dataclass
class SafetyNetCounts:
    """What the net did over a run."""

    agent_steps: int = 0
    """Agent-steps the net looked at (every agent alive, every step)."""
    acting_agent_steps: int = 0
    """Agent-steps whose command the net changed."""
    pairs: int = 0
    """Candidate pairs evaluated, summed over the steps."""
    steps: int = 0
    """Steps."""

    @property
    def acting_fraction(self) -> float | None:
        """``acting_agent_steps / agent_steps`` (None before any agent-step)."""
        return self.acting_agent_steps / self.agent_steps if self.agent_steps else None

    def as_dict(self) -> dict:
        """JSON-ready dict (metrics.json ``safety_net``)."""
        return {"acting_fraction": self.acting_fraction, "acting_agent_steps": self.acting_agent_steps,
                "agent_steps": self.agent_steps, "mean_candidate_pairs": self.pairs / self.steps if self.steps else None}


class SwarmSafetyNet:
    """The net for a whole simulated swarm (module docstring); ``apply`` is ``Swarm``'s ``command_filter``.

    ``d_min_m``: the map's designed spacing (``fisc_agent.map.separation.map_separation(body).d_min_m``);
    ``lag_s``: the vehicles' velocity lag (the plant's ``tau_v_s``), which sets the horizon; ``duct``:
    where the wall rule applies (None: nowhere); ``backend``: ``auto`` (numba when importable),
    ``numba`` or ``numpy`` (``keep_apart_pairs``)."""

    def __init__(self, d_min_m: float, config: SafetyNetConfig = SafetyNetConfig(), backend: str = "auto",
                 lag_s: float = 0.0, duct: DuctAxis | None = None) -> None:
        if not (np.isfinite(d_min_m) and d_min_m > 0):
            raise ValueError(f"safety net: d_min_m must be finite and > 0, is {d_min_m!r}")
        if backend not in ("auto", "numba", "numpy"):
            raise ValueError(f"safety net: backend {backend!r}: choose auto, numba or numpy")
        self.d_min_m = float(d_min_m)
        self.config = config
        self.lag_s = float(lag_s)
        """The vehicles' velocity lag [s]."""
        self.horizon_s = effective_horizon_s(config, self.lag_s)
        """The net's horizon for that lag [s]."""
        self.duct = duct
        """Where the wall rule applies (None: nowhere)."""
        self._kernel = None if backend == "numpy" else pairs_kernel()
        if self._kernel is None and backend == "numba":
            raise RuntimeError("safety net backend 'numba' requested but numba is not installed (pip install fisc[jit])")
        self.counts = SafetyNetCounts()

    def filtered_map(self, pos_m: np.ndarray, vel_m_s: np.ndarray, cmd_m_s: np.ndarray,
                     ids: np.ndarray) -> np.ndarray:
        """The commands ``cmd_m_s`` (n, 3) after the net, all in the map frame (a new array; no counting)."""
        return self._filter(pos_m, vel_m_s, cmd_m_s, ids)[0]

    def _filter(self, pos_m: np.ndarray, vel_m_s: np.ndarray, cmd_m_s: np.ndarray,
                ids: np.ndarray) -> tuple[np.ndarray, int]:
        """``filtered_map`` and the number of candidate pairs evaluated."""
        cfg = self.config
        reach = candidate_reach_m(self.d_min_m, cmd_m_s, self.horizon_s, vel_m_s) * (1.0 + _REACH_MARGIN)
        pairs = candidate_pairs(pos_m, reach)
        if self._kernel is None:
            return (keep_apart_pairs(pos_m, vel_m_s, cmd_m_s, ids, pairs, self.d_min_m, cfg, self.lag_s, self.duct),
                    pairs.shape[0])
        out = np.empty_like(cmd_m_s, dtype=float)
        d = self.duct
        duct = (np.array([d.x_lo_m, d.x_hi_m, d.center_yz_m[0], d.center_yz_m[1]]) if d is not None
                else np.array([np.inf, -np.inf, 0.0, 0.0]))  # an empty x range: the rule applies nowhere
        self._kernel(np.ascontiguousarray(pos_m, dtype=float), np.ascontiguousarray(vel_m_s, dtype=float),
                     np.ascontiguousarray(cmd_m_s, dtype=float), np.ascontiguousarray(ids, dtype=np.int64), pairs,
                     self.d_min_m, self.horizon_s, float(cfg.pass_margin_m), float(cfg.push_gain_1_s),
                     float(cfg.max_push_m_s),
                     COINCIDENT_M, LIMIT_TOL_M_S, duct, out)
        return out, pairs.shape[0]

    def apply(self, pos_m: np.ndarray, vel_ned_m_s: np.ndarray, cmd_ned_m_s: np.ndarray, ids: np.ndarray) -> None:
        """Adjust the NED commands ``cmd_ned_m_s`` (n, 3) in place (positions ``pos_m`` in the map frame,
        realised velocities ``vel_ned_m_s`` in NED, ``ids`` (n,)), and count what the net did."""
        n = cmd_ned_m_s.shape[0]
        self.counts.steps += 1
        self.counts.agent_steps += n
        if n < 2:
            return
        cmd = cmd_ned_m_s * _MAP_TO_NED
        out, n_pairs = self._filter(pos_m, vel_ned_m_s * _MAP_TO_NED, cmd, ids)
        self.counts.pairs += n_pairs
        self.counts.acting_agent_steps += int(np.count_nonzero(np.any(out != cmd, axis=1)))
        np.multiply(out, _MAP_TO_NED, out=cmd_ned_m_s)
