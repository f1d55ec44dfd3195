"""Offline model: a stock PX4 velocity loop flying the default map's axial command, with and without the
agent's drag feed-forward (``fisc_agent.flight.drag``; docs/deployment.md section 4a).

The vehicle is one axis: ``dv/dt = a_sp - c v`` with PX4's velocity PID ``a_sp = P e + I int(e) - D dv/dt + a_ff``
(stock ``MPC_XY_VEL_P/I/D_ACC`` 1.8 / 0.4 / 0.2, SIH's linear drag ``SIH_KDV`` 1 N s/m on 1 kg), 4 ms steps; the
agent sets ``v_sp`` at 20 Hz from the map's mean command on the axis, ``look-ahead`` seconds ahead (reach 1 m,
the secant beyond, as ``ParcelTracker._ahead``), and with the feed-forward sends ``a_ff = c_hat v_sp``.  Printed per
variant: the velocity nRMSE against the command at the vehicle, and the flown / fitted speed over 0.5 m slices
(the swarm's density profile goes as its inverse).  Without the feed-forward it reproduces what SIH's ground
truth showed (0.78-0.81 at the throat, 1.10-1.18 at the outlet).

    python tools/px4_loop_model.py [--drag 1.0]
"""

from __future__ import annotations

import argparse

import numpy as np


def axial_command():
    """The default map's mean command along its axis: a function of x [m], None outside the CVs."""
    from fisc_agent.flight.control import ScalarField
    from fisc_agent.map.lookup import CommandField
    from fisc_ground.maps.build import build_default_map

    sf = ScalarField(CommandField.from_map(build_default_map()))
    c = np.asarray(sf.centers)
    y0, z0 = float(np.median(c[:, 1])), float(np.median(c[:, 2]))

    def cmd(x: float) -> float | None:
        v = sf.command(x, y0, z0, 0, "mean")
        return None if v is None else v[0]

    return cmd, float(c[:, 0].min()), float(c[:, 0].max())


def fly(cmd, x0: float, lookahead_s: float, c_hat: float | None, drag_1_s: float = 1.0, p: float = 1.8,
        i: float = 0.4, d: float = 0.2, dt: float = 0.004, period_s: float = 0.05, reach_m: float = 1.0,
        on_at_speed: bool = False):
    """One pass: arrays of position, velocity and the command at the vehicle.  ``c_hat`` None: no feed-forward,
    PX4's integrator holds the drag at the start; else the feed-forward does (it came on at rest), or both
    (``on_at_speed``: it came on at the pass's start)."""
    x, v = x0, cmd(x0)
    integ = drag_1_s * v - (0.0 if c_hat is None or on_at_speed else c_hat) * v
    a = v_sp = a_ff = 0.0
    t = next_tick = 0.0
    out = []
    while True:
        if t >= next_tick:
            u = cmd(x)
            if u is None:
                break
            dist = lookahead_s * u
            step = min(dist, reach_m)
            ahead = cmd(x + step) if step > 1e-9 else u
            v_sp = u if ahead is None or step <= 1e-9 else u + dist / step * (ahead - u)
            a_ff = 0.0 if c_hat is None else c_hat * v_sp
            next_tick += period_s
        e = v_sp - v
        integ += i * e * dt
        a = p * e + integ - d * a + a_ff - drag_1_s * v
        v += a * dt
        x += v * dt
        t += dt
        out.append((x, v, u))
    return np.array(out)


def scores(track: np.ndarray, x_lo: float, x_hi: float) -> tuple[float, np.ndarray]:
    """Velocity nRMSE against the command at the vehicle, and flown / commanded speed per 0.5 m slice."""
    x, v, u = track.T
    edges = np.arange(x_lo, x_hi + 0.5, 0.5)
    k = np.digitize(x, edges)
    ratio = np.array([v[k == b].mean() / u[k == b].mean() for b in range(1, len(edges)) if (k == b).sum() > 3])
    return float(np.sqrt(np.mean((v - u) ** 2)) / np.mean(np.abs(u))), ratio


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--drag", type=float, default=1.0, help="the vehicle's linear drag [1/s] (SIH: 1)")
    a = ap.parse_args(argv)
    cmd, x_lo, x_hi = axial_command()
    c = a.drag
    variants = [("stock, look-ahead 0.93 s (identified)", 0.93, None), ("stock, no look-ahead", 0.0, None),
                ("feed-forward, look-ahead 0.4 s", 0.4, c), ("feed-forward, look-ahead 0.5 s", 0.5, c),
                ("feed-forward, look-ahead 0.93 s", 0.93, c), ("feed-forward 0.7 c, look-ahead 0.5 s", 0.5, 0.7 * c),
                ("feed-forward 1.3 c, look-ahead 0.5 s", 0.5, 1.3 * c)]
    for name, la, c_hat in variants:
        nrmse, r = scores(fly(cmd, x_lo, la, c_hat, drag_1_s=c), x_lo, x_hi)
        print(f"{name:40s} nRMSE {nrmse:.3f}   flown / fitted per 0.5 m: {r.min():.2f}-{r.max():.2f} "
              f"(std {r.std():.3f})")
    nrmse, r = scores(fly(cmd, x_lo, 0.5, c, drag_1_s=c, on_at_speed=True), x_lo, x_hi)
    print(f"{'feed-forward switched on at speed, 0.5 s':40s} nRMSE {nrmse:.3f}   flown / fitted per 0.5 m: "
          f"{r.min():.2f}-{r.max():.2f} (std {r.std():.3f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
